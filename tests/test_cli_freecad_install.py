"""``trueaxis freecad install [--dir DIR]``: the FreeCAD post script copied where FreeCAD looks for post processors."""

from __future__ import annotations

from trueaxis.cli import main
from trueaxis.postproc.hosts.freecad import SCRIPT_NAME, post_script_path


def test_install_into_a_given_folder_copies_the_script_and_names_it(tmp_path, capsys):
    assert main(["freecad", "install", "--dir", str(tmp_path / "Macro")]) == 0
    installed = tmp_path / "Macro" / SCRIPT_NAME
    assert installed.read_bytes() == post_script_path().read_bytes()
    assert capsys.readouterr().out.startswith(f"{installed}: installed")


def test_install_without_dir_uses_freecads_user_macro_folder(tmp_path, monkeypatch, capsys):
    # a FreeCAD that has run once (its XDG data folder exists) and no MacroPath in user.cfg
    monkeypatch.setenv("HOME", str(tmp_path))
    for name in ("XDG_CONFIG_HOME", "XDG_DATA_HOME"):
        monkeypatch.delenv(name, raising=False)
    (tmp_path / ".local" / "share" / "FreeCAD").mkdir(parents=True)
    assert main(["freecad", "install"]) == 0
    assert (tmp_path / ".local" / "share" / "FreeCAD" / "Macro" / SCRIPT_NAME).is_file()


def test_install_again_replaces_the_script(tmp_path):
    target = tmp_path / SCRIPT_NAME
    target.write_text("old")
    assert main(["freecad", "install", "--dir", str(tmp_path)]) == 0
    assert target.read_bytes() == post_script_path().read_bytes()
    assert sorted(p.name for p in tmp_path.iterdir()) == [SCRIPT_NAME]  # no temporary file left


def test_install_into_a_folder_that_cannot_be_made_exits_2_with_one_line(tmp_path, capsys):
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    assert main(["freecad", "install", "--dir", str(blocker / "Macro")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("trueaxis freecad: cannot install into") and "Traceback" not in err[0]
