"""Cloud I/O: round trips, files written by hand in each PLY flavour, CSV/XYZ, an independent reader (open3d), and
refusal of every kind of bad input with a one-line message naming the file."""

import numpy as np
import pytest

from trueaxis.inspect.cloud import Cloud, CloudError, check_extent, read_cloud, write_cloud_ply


@pytest.fixture
def cloud():
    rng = np.random.default_rng(11)
    points = rng.uniform(-40.0, 40.0, (257, 3))
    normals = rng.normal(size=(257, 3))
    return points, normals


def refused(path, match=None):
    """read_cloud(path) must raise CloudError, on one line, naming the file; returns the message."""
    with pytest.raises(CloudError) as info:
        read_cloud(path)
    message = str(info.value)
    assert str(path) in message and "\n" not in message, message
    if match is not None:
        assert match in message, message
    return message


def ply_header(fmt, count, properties, extra_elements=""):
    lines = ["ply", f"format {fmt} 1.0", "comment written by hand", f"element vertex {count}"]
    lines += [f"property {t} {n}" for t, n in properties]
    return ("\n".join(lines) + "\n" + extra_elements + "end_header\n").encode("ascii")


# ------------------------------------------------------------------------------------------------------- round trips

@pytest.mark.parametrize("binary", [True, False])
def test_ply_round_trip_is_exact(tmp_path, cloud, binary):
    points, normals = cloud
    path = tmp_path / "part.ply"
    write_cloud_ply(path, points, normals, binary=binary, comments=["part nas979", "units mm"])
    back = read_cloud(path)
    assert isinstance(back, Cloud) and back.source == str(path) and len(back) == len(points)
    # doubles in binary, 17 significant digits in ascii: both read back bit for bit
    np.testing.assert_array_equal(back.points, points)
    np.testing.assert_allclose(back.normals, normals / np.linalg.norm(normals, axis=1)[:, None], rtol=0, atol=1e-15)
    assert b"comment part nas979" in path.read_bytes()[:400]
    write_cloud_ply(path, points, binary=binary)  # over an existing file, and without normals
    assert read_cloud(path).normals is None


@pytest.mark.parametrize("fmt, order", [("binary_big_endian", ">"), ("binary_little_endian", "<")])
def test_binary_ply_written_by_hand_with_other_properties_and_faces(tmp_path, cloud, fmt, order):
    # float x y z (as most scanners write), extra properties in between, a face element after the vertices
    points, normals = cloud
    dtype = np.dtype([("x", order + "f4"), ("red", "u1"), ("y", order + "f4"), ("z", order + "f4"),
                      ("nx", order + "f8"), ("ny", order + "f8"), ("nz", order + "f8"), ("quality", order + "i2")])
    table = np.zeros(len(points), dtype=dtype)
    for i, name in enumerate("xyz"):
        table[name] = points[:, i]
    for i, name in enumerate(("nx", "ny", "nz")):
        table[name] = normals[:, i]
    table["red"], table["quality"] = 200, -7
    face = np.array([(3, 0, 1, 2)], dtype=[("n", "u1"), ("a", order + "i4"), ("b", order + "i4"), ("c", order + "i4")])
    header = ply_header(fmt, len(points), [("float", "x"), ("uchar", "red"), ("float", "y"), ("float", "z"),
                                            ("double", "nx"), ("double", "ny"), ("double", "nz"), ("short", "quality")],
                        "element face 1\nproperty list uchar int vertex_indices\n")
    path = tmp_path / f"{fmt}.ply"
    path.write_bytes(header + table.tobytes() + face.tobytes())
    back = read_cloud(path)
    # the reader returns float64 of the float32 values stored: exactly the float32 rounding of the inputs
    np.testing.assert_array_equal(back.points, points.astype(np.float32).astype(np.float64))
    np.testing.assert_allclose(back.normals, normals / np.linalg.norm(normals, axis=1)[:, None], atol=1e-15)


def test_ascii_ply_written_by_hand_with_other_properties_and_faces(tmp_path):
    body = "1.5 2 3 7 0 0 2\n-4 5e-1 6.25 8 0 3 0\n0 0 0 9 1 0 0\n3 0 1 2\n"
    header = ply_header("ascii", 3, [("double", "x"), ("float", "y"), ("float", "z"), ("uchar", "intensity"),
                                     ("float", "nx"), ("float", "ny"), ("float", "nz")],
                        "element face 1\nproperty list uchar int vertex_indices\n")
    path = tmp_path / "hand.ply"
    path.write_bytes(header + body.encode())
    back = read_cloud(path)
    np.testing.assert_array_equal(back.points, [[1.5, 2, 3], [-4, 0.5, 6.25], [0, 0, 0]])
    np.testing.assert_array_equal(back.normals, [[0, 0, 1], [0, 1, 0], [1, 0, 0]])


@pytest.mark.parametrize("fmt", ["ascii", "binary_little_endian"])
def test_ply_property_names_are_case_insensitive_as_a_csv_header_is(tmp_path, cloud, fmt):
    """``property double X`` (some exporters write upper case) was refused as "no property x, y, z", where a CSV
    header's X Y Z was read: both are read case-insensitively, normals (NX Ny nz) too; x and X both is refused."""
    points, normals = cloud
    names = ["X", "Y", "Z", "NX", "Ny", "nz"]
    if fmt == "ascii":
        body = "".join(" ".join(repr(float(v)) for v in row) + "\n" for row in np.hstack([points, normals]))
        body = body.encode("ascii")
    else:
        table = np.zeros(len(points), dtype=[(n, "<f8") for n in names])
        for i, n in enumerate(names):
            table[n] = np.hstack([points, normals])[:, i]
        body = table.tobytes()
    path = tmp_path / "upper.ply"
    path.write_bytes(ply_header(fmt, len(points), [("double", n) for n in names]) + body)
    back = read_cloud(path)
    np.testing.assert_array_equal(back.points, points)
    np.testing.assert_allclose(back.normals, normals / np.linalg.norm(normals, axis=1)[:, None], rtol=0, atol=1e-15)
    (tmp_path / "twice.ply").write_bytes(ply_header("ascii", 1, [("float", n) for n in ("x", "X", "y", "z")])
                                         + b"1 2 3 4\n")
    refused(tmp_path / "twice.ply", "property x twice (names read in any case: x, X)")


def test_open3d_reads_the_same_points_from_our_binary_ply(tmp_path, cloud):
    import open3d as o3d  # a dependency of the package: missing, the test fails

    points, normals = cloud
    path = tmp_path / "o3d.ply"
    write_cloud_ply(path, points, normals)
    theirs = o3d.io.read_point_cloud(str(path))
    np.testing.assert_array_equal(np.asarray(theirs.points), points)
    # open3d keeps the normals as written; ours are normalised
    np.testing.assert_allclose(np.asarray(theirs.normals), normals, rtol=0, atol=1e-15)
    # and the other way round: a binary PLY written by open3d reads back the same
    theirs_path = tmp_path / "by_o3d.ply"
    o3d.io.write_point_cloud(str(theirs_path), theirs, write_ascii=False)
    np.testing.assert_array_equal(read_cloud(theirs_path).points, points)


def test_csv_with_and_without_header_and_xyz(tmp_path):
    points = np.array([[1.0, 2.0, 3.0], [-4.5, 0.25, 1e-3], [7.0, 8.0, 9.0]])
    normals = np.array([[0.0, 0.0, 2.0], [0.0, -1.0, 0.0], [3.0, 4.0, 0.0]])
    unit = normals / np.linalg.norm(normals, axis=1)[:, None]
    rows6 = np.hstack([points, normals]).tolist()
    points_rows = points.tolist()

    (tmp_path / "plain.csv").write_text("\n".join(",".join(map(repr, row)) for row in points_rows) + "\n")
    (tmp_path / "header.csv").write_text("x,y,z,nx,ny,nz\n" + "\n".join(",".join(map(repr, r)) for r in rows6))
    # header in another order, with an extra column and a comment line, spaces after the commas
    (tmp_path / "shuffled.csv").write_text("# probe 2 mm\nZ, id, X, Y\n" +
                                           "\n".join(f"{z!r}, {i}, {x!r}, {y!r}" for i, (x, y, z) in enumerate(points_rows)))
    (tmp_path / "spaces.csv").write_text("\n".join(" ".join(map(repr, r)) for r in rows6) + "\n")
    (tmp_path / "points.xyz").write_text("\n".join("\t".join(map(repr, r)) for r in points_rows) + "\n")
    (tmp_path / "normals.XYZ").write_text("\n".join("  ".join(map(repr, r)) for r in rows6))

    for name, has_normals in [("plain.csv", False), ("header.csv", True), ("shuffled.csv", False),
                              ("spaces.csv", True), ("points.xyz", False), ("normals.XYZ", True)]:
        back = read_cloud(tmp_path / name)
        np.testing.assert_array_equal(back.points, points, err_msg=name)
        if has_normals:
            np.testing.assert_allclose(back.normals, unit, atol=1e-15, err_msg=name)
        else:
            assert back.normals is None, name


# ---------------------------------------------------------------------------------------------------------- refusals

def test_empty_and_header_only_files_are_refused(tmp_path):
    for name in ("empty.ply", "empty.csv", "empty.xyz"):
        (tmp_path / name).write_bytes(b"")
        refused(tmp_path / name, "empty")
    (tmp_path / "blank.xyz").write_text("\n  \n")
    refused(tmp_path / "blank.xyz", "empty")
    (tmp_path / "header_only.ply").write_bytes(ply_header("binary_little_endian", 0, [("float", c) for c in "xyz"]))
    refused(tmp_path / "header_only.ply", "no points")
    (tmp_path / "header_only.csv").write_text("x,y,z\n")
    refused(tmp_path / "header_only.csv", "no points")


def test_nan_and_inf_are_refused_saying_how_many_and_where(tmp_path, cloud):
    points = cloud[0].copy()
    points[[5, 9, 100], [0, 2, 1]] = [np.nan, np.inf, -np.inf]
    path = tmp_path / "nan.ply"
    header = ply_header("binary_little_endian", len(points), [("double", c) for c in "xyz"])
    path.write_bytes(header + points.astype("<f8").tobytes())
    message = refused(path, "3 of 257 points have NaN or infinite coordinates")
    assert "point 5" in message and "nan" in message
    (tmp_path / "nan.csv").write_text("x,y,z\n1,2,3\n4,nan,6\n")
    refused(tmp_path / "nan.csv", "1 of 2 points")
    (tmp_path / "inf.xyz").write_text("1 2 3\n4 5 inf\n7 8 9\n")
    refused(tmp_path / "inf.xyz", "point 1")
    (tmp_path / "inf.ply").write_bytes(ply_header("ascii", 2, [("float", c) for c in "xyz"]) + b"1 2 3\n-inf 0 0\n")
    refused(tmp_path / "inf.ply", "1 of 2 points")


def test_truncated_files_are_refused(tmp_path, cloud):
    path = tmp_path / "whole.ply"
    write_cloud_ply(path, *cloud)
    data = path.read_bytes()
    (tmp_path / "cut.ply").write_bytes(data[:-7])
    refused(tmp_path / "cut.ply", "truncated")
    (tmp_path / "cut_header.ply").write_bytes(data[:60])
    refused(tmp_path / "cut_header.ply", "end_header")
    write_cloud_ply(path, *cloud, binary=False)
    lines = path.read_bytes().splitlines(keepends=True)
    (tmp_path / "cut_ascii.ply").write_bytes(b"".join(lines[:-10]))
    refused(tmp_path / "cut_ascii.ply", "truncated")
    (tmp_path / "cut_line.ply").write_bytes(b"".join(lines[:-1]) + lines[-1][:20])  # last row half written
    refused(tmp_path / "cut_line.ply")
    # more data than the header declares: a wrong count, not silently dropped
    (tmp_path / "long.ply").write_bytes(data + b"\x00" * 24)
    refused(tmp_path / "long.ply", "after its")


def test_unknown_extension_garbage_and_missing_files_are_refused(tmp_path, cloud):
    (tmp_path / "cloud.stl").write_bytes(b"solid x\nendsolid x\n")
    refused(tmp_path / "cloud.stl", "unknown cloud extension")
    refused(tmp_path / "missing.ply", "cannot read")
    garbage = np.random.default_rng(3).integers(0, 256, 4096, dtype=np.uint8).tobytes()
    for name in ("garbage.ply", "garbage.csv", "garbage.xyz"):
        (tmp_path / name).write_bytes(garbage)
        refused(tmp_path / name)
    # a PLY header with garbage where the vertices should be (ascii) and a non-numeric CSV row
    (tmp_path / "garbage_body.ply").write_bytes(ply_header("ascii", 2, [("float", c) for c in "xyz"]) + garbage[:50])
    refused(tmp_path / "garbage_body.ply")
    (tmp_path / "words.csv").write_text("x,y,z\n1,2,3\n4,five,6\n")
    refused(tmp_path / "words.csv", "cannot read CSV data row 2 (not a number)")
    (tmp_path / "ragged.xyz").write_text("1 2 3\n4 5\n")
    refused(tmp_path / "ragged.xyz")
    (tmp_path / "four.xyz").write_text("1 2 3 4\n5 6 7 8\n")
    refused(tmp_path / "four.xyz", "expected 3")
    # a PLY without z, and one with only some normal components
    (tmp_path / "noz.ply").write_bytes(ply_header("ascii", 1, [("float", "x"), ("float", "y")]) + b"1 2\n")
    refused(tmp_path / "noz.ply", "no property z")
    props = [("float", c) for c in ("x", "y", "z", "nx", "ny")]
    (tmp_path / "nxny.ply").write_bytes(ply_header("ascii", 1, props) + b"1 2 3 0 1\n")
    refused(tmp_path / "nxny.ply", "not all of nx ny nz")


def test_duplicate_points_counts_exact_repeats_even_where_hashes_collide(monkeypatch):
    """n minus the distinct rows: a cloud given three times has 2n repeats; points equal in two coordinates only
    are not repeats; -0.0 is 0.0. With a hash that collides on purpose (|x| alone) the count is the same."""
    from trueaxis.inspect import cloud as cloud_module
    from trueaxis.inspect.cloud import duplicate_points

    rng = np.random.default_rng(5)
    points = rng.uniform(-40.0, 40.0, (1000, 3))
    points[500:600, 0] = points[:100, 0]  # x shared with another point, y and z not
    tripled = np.vstack([points, points, points])
    some = np.vstack([points, points[[3, 3, 7, 510]]])
    signed = np.array([[0.0, 1.0, 2.0], [-0.0, 1.0, 2.0], [0.0, -1.0, 2.0], [0.0, 1.0, -0.0], [-0.0, 1.0, 0.0]])
    expected = [(points, 0), (tripled, 2000), (some, 4), (points[:1], 0), (signed, 2)]
    def first_of_each(cloud):  # the reference: np.unique's first index of each distinct row (-0.0 as 0.0)
        keep = np.zeros(len(cloud), bool)
        keep[np.unique(cloud + 0.0, axis=0, return_index=True)[1]] = True
        return ~keep

    for cloud, count in expected:
        assert duplicate_points(cloud) == count == len(cloud) - len(np.unique(cloud, axis=0))
        np.testing.assert_array_equal(cloud_module.repeated_points(cloud), first_of_each(cloud))
    # |x| alone: a hash that -0.0 and 0.0 share, as the real one, and different points share often
    monkeypatch.setattr(cloud_module, "_row_hash", lambda bits: bits[:, 0] & ~np.uint64(1 << 63))
    for cloud, count in expected:
        assert duplicate_points(cloud) == count
        np.testing.assert_array_equal(cloud_module.repeated_points(cloud), first_of_each(cloud))


def test_read_cloud_drops_exact_repeats_keeping_the_first_of_each_in_order(tmp_path):
    """A cloud written twice (and a few points three times) reads as the cloud written once, normals with their
    points, and says how many it dropped; points equal in two coordinates only stay."""
    rng = np.random.default_rng(7)
    points = rng.uniform(-40.0, 40.0, (500, 3))
    points[100:110, :2] = points[:10, :2]  # x and y shared, z not: distinct points
    normals = rng.normal(size=(500, 3))
    normals /= np.linalg.norm(normals, axis=1)[:, None]
    again = [3, 3, 250, 499]
    write_cloud_ply(tmp_path / "twice.ply", np.vstack([points, points, points[again]]),
                    np.vstack([normals, -normals, normals[again]]))
    back = read_cloud(tmp_path / "twice.ply")
    np.testing.assert_array_equal(back.points, points)
    np.testing.assert_allclose(back.normals, normals, rtol=0, atol=1e-15)  # the first of each, not the flipped copy
    assert back.repeats_dropped == 504 and len(back) == 500
    (tmp_path / "once.csv").write_text("".join("%.17g,%.17g,%.17g\n" % tuple(p) for p in points))
    assert read_cloud(tmp_path / "once.csv").repeats_dropped == 0


def test_zero_length_normals_are_refused(tmp_path):
    (tmp_path / "zero.xyz").write_text("1 2 3 0 0 1\n4 5 6 0 0 0\n")
    refused(tmp_path / "zero.xyz", "1 of 2 normals have zero length")


def test_nothing_is_written_for_a_cloud_we_would_refuse(tmp_path, cloud):
    points, normals = cloud
    bad = points.copy()
    bad[17, 1] = np.nan
    target = tmp_path / "out.ply"
    with pytest.raises(CloudError, match="NaN"):
        write_cloud_ply(target, bad)
    assert list(tmp_path.iterdir()) == []
    zero = normals.copy()
    zero[3] = 0.0
    with pytest.raises(CloudError, match="zero length"):
        write_cloud_ply(target, points, zero, binary=False)
    with pytest.raises(CloudError, match="no points"):
        write_cloud_ply(target, np.zeros((0, 3)))
    assert list(tmp_path.iterdir()) == []
    # an existing file is left as it was, and no temporary file stays behind
    write_cloud_ply(target, points)
    before = target.read_bytes()
    with pytest.raises(CloudError):
        write_cloud_ply(target, bad)
    assert target.read_bytes() == before and [p.name for p in tmp_path.iterdir()] == ["out.ply"]
    with pytest.raises(ValueError, match="shape"):
        write_cloud_ply(target, points[:, :2])
    with pytest.raises(ValueError, match="single lines"):
        write_cloud_ply(target, points, comments=["two\nlines"])


def test_check_extent_names_the_part_the_axis_and_the_distance():
    box_min, box_max = np.array([-45.0, -45.0, 0.0]), np.array([45.0, 45.0, 25.0])
    inside = np.array([[-40.0, 0.0, 0.0], [40.0, 39.0, 20.0], [45.4, 0.0, 25.4]])
    check_extent(inside, box_min, box_max, tolerance_mm=0.5, part="nas979")  # within the 0.5 mm allowance
    # a cloud left in the machine frame: shifted 153.2 mm in X (and 12 mm in Z)
    shifted = inside + [153.2, 0.0, -12.0]
    with pytest.raises(CloudError) as info:
        check_extent(shifted, box_min, box_max, tolerance_mm=0.5, part="nas979")
    message = str(info.value)
    assert "nas979" in message and "153.6 mm in X" in message and "12.0 mm in Z" in message and "in mm?" in message
    with pytest.raises(ValueError):
        check_extent(inside, box_max, box_min, tolerance_mm=0.5)


@pytest.mark.parametrize("unit, factor", [("cm", 10.0), ("inch", 25.4), ("m", 1000.0)])
def test_a_cloud_too_small_for_the_part_is_refused_as_a_unit_mistake(unit, factor):
    # A slot block's cloud written in metres (or cm, inches) and read as mm shrinks into a corner of the part, where
    # every point passed as lying on the top face: 2.15 um RMS, exit 0 (a QA pass). Refused, saying why.
    box_min, box_max = np.array([-80.0, -50.0, -30.0]), np.array([80.0, 50.0, 0.0])
    rng = np.random.default_rng(3)
    measured = box_min + (box_max - box_min) * (0.1 + 0.8 * rng.random((500, 3)))  # spans 80 % of the block
    check_extent(measured, box_min, box_max, tolerance_mm=0.5, part="slots")
    with pytest.raises(CloudError, match=r"the cloud spans .* where the slots part spans 160 mm .*: is it in mm\?"):
        check_extent(measured / factor, box_min, box_max, tolerance_mm=0.5, part="slots")


# ---------------------------------------------------------------- files as CMM software and other programs write them

CMM_POINTS = np.array([[12.5, -3.25, 4.0], [-7.125, 0.5, 19.75], [0.0, 40.0, -2.5], [3.0625, 1.5, 0.001]])
CMM_VECTORS = np.array([[0.0, 0.0, 1.0], [0.6, 0.8, 0.0], [0.0, -1.0, 0.0], [0.28, 0.0, 0.96]])


def _decimal_comma(value):
    return f"{value:.4f}".replace(".", ",")


def test_cmm_point_exports_with_names_delimiters_and_decimal_commas(tmp_path):
    # the shapes CMM software writes (Calypso / PC-DMIS / PolyWorks point exports): a name column, upper-case
    # header X Y Z I J K, ';' with decimal commas (European locale), tabs, units in the header, no header at all
    names = [f"Pt{k + 1}" for k in range(len(CMM_POINTS))]
    rows = [(n, *p, *v) for n, p, v in zip(names, CMM_POINTS, CMM_VECTORS)]
    files = {
        "semicolon.csv": "Name;X;Y;Z;I;J;K\n" + "".join(
            f"{r[0]};" + ";".join(_decimal_comma(v) for v in r[1:]) + "\n" for r in rows),
        "comma_named.csv": "Name,X,Y,Z,I,J,K\n" + "".join(",".join([r[0]] + [f"{v:.4f}" for v in r[1:]]) + "\n"
                                                           for r in rows),
        "quoted.csv": '"Name","X [mm]","Y [mm]","Z [mm]","I","J","K"\r\n' + "".join(
            ",".join([f'"{r[0]}"'] + [f"{v:.4f}" for v in r[1:]]) + "\r\n" for r in rows),
        "tab.txt": "x\ty\tz\tnx\tny\tnz\n" + "".join("\t".join(f"{v:.4f}" for v in r[1:]) + "\n" for r in rows),
        "tab_comma.csv": "".join("\t".join(_decimal_comma(v) for v in r[1:]) + "\n" for r in rows),
        "name_no_header.csv": "".join(f"{r[0]} " + " ".join(f"{v:.4f}" for v in r[1:]) + "\n" for r in rows),
        "semicolon_no_vectors.csv": "name;x;y;z;dev\n" + "".join(
            f"{r[0]};" + ";".join(_decimal_comma(v) for v in r[1:4]) + ";0,001\n" for r in rows),
    }
    for file, text in files.items():
        (tmp_path / file).write_bytes(text.encode("ascii"))
        back = read_cloud(tmp_path / file)
        np.testing.assert_allclose(back.points, CMM_POINTS, rtol=0, atol=5e-5, err_msg=file)
        if "no_vectors" in file:
            assert back.normals is None
        else:
            np.testing.assert_allclose(back.normals, CMM_VECTORS, rtol=0, atol=1e-4, err_msg=file)


def test_csv_exports_that_cannot_be_read_unambiguously_are_refused(tmp_path):
    (tmp_path / "two.csv").write_text("Name;X;Y\nP1;1,0;2,0\n")
    refused(tmp_path / "two.csv", "no column z")
    (tmp_path / "ij.csv").write_text("x,y,z,i,j\n1,2,3,0,0\n")
    refused(tmp_path / "ij.csv", "not all of nx ny nz")
    (tmp_path / "ragged.csv").write_text("P1;1,0;2,0;3,0\nP2;1,0;2,0;3,0;4,0\n")
    refused(tmp_path / "ragged.csv", "row 2")
    (tmp_path / "four.csv").write_text("1,2,3,4\n")
    refused(tmp_path / "four.csv", "4 numeric columns")


def test_decimal_commas_with_comma_delimiters_are_refused_naming_them(tmp_path):
    """Decimal commas and ',' between the fields: read as six numbers, 1,4240,34,9056,18,9010 was refused as "cloud
    extent exceeds the part by 9947 mm in Y". Refused naming the decimal commas, with or without a header or a name
    column, normals too; the same numbers with ';' are read; an integer cloud with normals is read as before."""
    rows = ["1,4240,34,9056,18,9010", "-33,2581,20,1618,7,5060", "-0,0054,34,6489,19,0000"]
    said = "1,4240,34,9056,18,9010': 6 fields, each second one 4 digits, no '.'), which cannot be told apart"
    for file, text in (("plain.csv", rows), ("header.csv", ["x,y,z", *rows]),
                       ("named.csv", ["Name,X,Y,Z", *(f"P{k},{r}" for k, r in enumerate(rows))])):
        (tmp_path / file).write_text("\n".join(text) + "\n")
        message = refused(tmp_path / file, said)
        assert "looks written with decimal commas and ',' between the fields" in message
        assert "export with ';' or tab between the fields (a ',' is then read as the decimal comma)" in message
    (tmp_path / "normals.csv").write_text("".join(r + ",0,0000,-0,6000,0,8000\n" for r in rows))
    refused(tmp_path / "normals.csv", "12 fields, each second one 4 digits")
    (tmp_path / "semicolon.csv").write_text("1,4240;34,9056;18,9010\n-33,2581;20,1618;7,5060\n")
    np.testing.assert_array_equal(read_cloud(tmp_path / "semicolon.csv").points,
                                  [[1.424, 34.9056, 18.901], [-33.2581, 20.1618, 7.506]])
    (tmp_path / "integers.csv").write_text("10,20,30,0,0,1\n-10,25,35,0,1,0\n")
    back = read_cloud(tmp_path / "integers.csv")
    np.testing.assert_array_equal(back.points, [[10, 20, 30], [-10, 25, 35]])
    np.testing.assert_array_equal(back.normals, [[0, 0, 1], [0, 1, 0]])


def test_whitespace_separated_decimal_commas_are_read_as_decimal_commas(tmp_path):
    """A European CMM text export with spaces between the fields and decimal commas (a QA pass's
    '39,3006 0,0000 -5,9147') was refused as "CSV rows have 2 numeric columns" (',' taken as the delimiter). Every
    ',' inside a field of digits, never between fields: read, with or without a header, a name column or normals,
    as the same numbers written with points; a ',' CSV is read with ',' between the fields as before."""
    rows = [(39.3006, 0.0, -5.9147), (39.2872, 1.1244, -5.9118), (39.2429, 2.248, -5.9032)]
    normals = [(0.9659, 0.0, -0.2588), (0.9646, 0.0506, -0.2588), (0.9606, 0.1010, -0.2588)]
    dc = _decimal_comma
    files = {"plain.txt": ["39,3006 0,0000 -5,9147", "39,2872 1,1244 -5,9118", "39,2429 2,2480 -5,9032"],
             "header.txt": ["X Y Z", *(" ".join(dc(v) for v in r) for r in rows)],
             "named.csv": [f"P{k}  " + "  ".join(dc(v) for v in r) for k, r in enumerate(rows)],
             "normals.txt": [" ".join(dc(v) for v in (*r, *n)) for r, n in zip(rows, normals)]}
    for file, lines in files.items():
        (tmp_path / file).write_text("\n".join(lines) + "\n")
        back = read_cloud(tmp_path / file)
        np.testing.assert_allclose(back.points, rows, rtol=0, atol=1e-12, err_msg=file)
        if file == "normals.txt":
            expected = np.array(normals) / np.linalg.norm(normals, axis=1)[:, None]
            np.testing.assert_allclose(back.normals, expected, rtol=0, atol=1e-12)
        else:
            assert back.normals is None, file
    (tmp_path / "spaced.csv").write_text("39.3006, 0.0, -5.9147\n39.2872, 1.1244, -5.9118\n")  # ', ' between
    np.testing.assert_array_equal(read_cloud(tmp_path / "spaced.csv").points, rows[:2])


def test_e57_written_by_libe57format_reads_in_mm_with_its_pose(tmp_path):
    import pye57  # a dependency (pyproject): a missing one fails, never skips
    from scipy.spatial.transform import Rotation

    rng = np.random.default_rng(5)
    local_m = rng.uniform(-0.05, 0.05, (500, 3))  # E57 stores metres
    quaternion_wxyz = np.array([np.cos(0.15), 0.0, 0.0, np.sin(0.15)])  # 0.3 rad about z
    translation_m = np.array([0.01, -0.02, 0.005])
    e57 = pye57.E57(str(tmp_path / "scan.e57"), mode="w")
    e57.write_scan_raw({"cartesianX": local_m[:, 0], "cartesianY": local_m[:, 1], "cartesianZ": local_m[:, 2]},
                       rotation=quaternion_wxyz, translation=translation_m)
    e57.write_scan_raw({"cartesianX": local_m[:7, 0], "cartesianY": local_m[:7, 1], "cartesianZ": local_m[:7, 2]})
    e57.close()
    back = read_cloud(tmp_path / "scan.e57")
    rotation = Rotation.from_quat(np.r_[quaternion_wxyz[1:], quaternion_wxyz[0]]).as_matrix()
    expected = np.vstack([local_m @ rotation.T + translation_m, local_m[:7]]) * 1000.0
    # pye57 writes the coordinates as float32 metres: 2^-24 of 0.1 m is 6 nm
    np.testing.assert_allclose(back.points, expected, rtol=0, atol=1e-5)
    assert back.normals is None
    (tmp_path / "junk.e57").write_bytes(b"ASTM-E57" + bytes(100))
    refused(tmp_path / "junk.e57", "E57")


DMIS_OUTPUT = """\
$$ DMIS output of a point measurement, written by hand following ANSI/DMIS 105.2 (part 1, 5.2)
DMISMD/'CONE_CHECK',CURRENT
UNITS/{unit},ANGDEC
F(PT1)=FEAT/POINT,CART,12.5,-3.25,4,0,0,1
MEAS/POINT,F(PT1),1
PTMEAS/CART,12.5,-3.25,4,0,0,1
ENDMES
FA(PT1)=FEAT/POINT,CART,{p[0][0]},{p[0][1]},{p[0][2]},0.000000,0.000000,1.000000
FA(PT2)=FEAT/POINT,CART,{p[1][0]},{p[1][1]},$
    {p[1][2]},0.600000,0.800000,0.000000
$$ a circle's actual is a feature, not a point: skipped
FA(CIR1)=FEAT/CIRCLE,INNER,CART,0,0,0,0,0,1,20.001
FA(PT_3)=FEAT/POINT,CART,{p[2][0]},{p[2][1]},{p[2][2]},0.000000,-1.000000,0.000000
FA(P4) = FEAT/POINT, CART, {p[3][0]}, {p[3][1]}, {p[3][2]}, 0.280000, 0.000000, 0.960000
ENDFIL
"""


@pytest.mark.parametrize("unit, scale", [("MM", 1.0), ("INCH", 25.4)])
def test_dmis_output_measured_points_are_read_in_mm_and_nominals_are_not(tmp_path, unit, scale):
    values = [[f"{v / scale:.9f}" for v in p] for p in CMM_POINTS]
    (tmp_path / "run.dmo").write_text(DMIS_OUTPUT.format(unit=unit, p=values))
    back = read_cloud(tmp_path / "run.dmo")
    # four actual points (PT1 once: its nominal F(PT1) and PTMEAS target are not measurements)
    np.testing.assert_allclose(back.points, CMM_POINTS, rtol=0, atol=1e-7)
    np.testing.assert_allclose(back.normals, CMM_VECTORS, rtol=0, atol=1e-12)


def test_dmis_program_without_actuals_is_refused(tmp_path):
    program = "DMISMD/'P',CURRENT\nUNITS/MM,ANGDEC\nF(PT1)=FEAT/POINT,CART,1,2,3,0,0,1\nMEAS/POINT,F(PT1),1\n" \
              "PTMEAS/CART,1,2,3,0,0,1\nENDMES\nFA(C1)=FEAT/CIRCLE,INNER,CART,0,0,0,0,0,1,20\nENDFIL\n"
    (tmp_path / "prog.dmi").write_text(program)
    message = refused(tmp_path / "prog.dmi", "no measured DMIS point")
    assert "1 CIRCLE" in message
    (tmp_path / "pol.dmo").write_text("FA(P1)=FEAT/POINT,POL,10,45,3,0,0,1\n")
    refused(tmp_path / "pol.dmo", "only CART")
    (tmp_path / "feet.dmo").write_text("UNITS/FURLONG,ANGDEC\nFA(P1)=FEAT/POINT,CART,1,2,3\n")
    refused(tmp_path / "feet.dmo", "FURLONG")


# ------------------------------------------------------------------------------------------- deviation outputs

def test_deviation_ply_is_a_scalar_field_for_plyfile_and_cloudcompare(tmp_path):
    import os
    import subprocess

    from cloudcompare_helpers import require_cloudcompare
    from plyfile import PlyData
    from trueaxis.inspect.cloud import write_deviation_ply

    rng = np.random.default_rng(3)
    points = rng.uniform(-40, 40, (300, 3))
    deviation_um = rng.uniform(-30, 30, 300)
    normals = rng.normal(size=(300, 3))
    write_deviation_ply(tmp_path / "dev.ply", points, deviation_um, normals, comments=["part nas979"])
    vertex = PlyData.read(str(tmp_path / "dev.ply"))["vertex"]
    np.testing.assert_array_equal(vertex["scalar_deviation_um"], deviation_um)
    np.testing.assert_array_equal(np.column_stack([vertex["x"], vertex["y"], vertex["z"]]), points)
    np.testing.assert_array_equal(read_cloud(tmp_path / "dev.ply").points, points)  # ours ignores the field

    exe = require_cloudcompare()
    env = dict(os.environ, QT_QPA_PLATFORM="offscreen")
    run = subprocess.run([exe, "-SILENT", "-AUTO_SAVE", "OFF", "-O", str(tmp_path / "dev.ply"), "-C_EXPORT_FMT",
                          "ASC", "-ADD_HEADER", "-SAVE_CLOUDS", "FILE", str(tmp_path / "cc.asc")],
                         capture_output=True, text=True, env=env, timeout=300, cwd=tmp_path)
    assert run.returncode == 0, run.stdout[-1000:] + run.stderr[-1000:]
    header = (tmp_path / "cc.asc").read_text().splitlines()[0].lstrip("/").split()
    assert "deviation_um" in header, header  # CloudCompare loaded our property as its scalar field
    table = np.loadtxt(tmp_path / "cc.asc", comments="//")
    # CloudCompare keeps coordinates and scalar fields as float32
    np.testing.assert_allclose(table[:, header.index("deviation_um")], deviation_um, rtol=2e-7, atol=1e-5)
    np.testing.assert_allclose(table[:, :3], points, rtol=0, atol=1e-5)
    # and CloudCompare's ASCII export, header and all, reads back as a cloud with its normals
    back = read_cloud(tmp_path / "cc.asc")
    np.testing.assert_allclose(back.points, points, rtol=0, atol=1e-5)
    cosine = np.sum(back.normals * normals / np.linalg.norm(normals, axis=1)[:, None], axis=1)
    assert np.degrees(np.arccos(np.clip(cosine, -1, 1))).max() < 0.5


def test_a_ply_written_by_cloudcompare_with_scalar_fields_is_read(tmp_path):
    import os
    import subprocess

    from cloudcompare_helpers import require_cloudcompare

    exe = require_cloudcompare()
    rng = np.random.default_rng(8)
    points = rng.uniform(-40, 40, (200, 3))
    normals = rng.normal(size=(200, 3))
    from trueaxis.inspect.cloud import write_deviation_ply

    write_deviation_ply(tmp_path / "in.ply", points, np.arange(200) * 0.5, normals)
    env = dict(os.environ, QT_QPA_PLATFORM="offscreen")
    run = subprocess.run([exe, "-SILENT", "-AUTO_SAVE", "OFF", "-O", "in.ply", "-C_EXPORT_FMT", "PLY",
                          "-SAVE_CLOUDS", "FILE", "cc.ply"], capture_output=True, text=True, env=env, timeout=300,
                         cwd=tmp_path)
    assert run.returncode == 0 and (tmp_path / "cc.ply").is_file(), run.stdout[-1000:]
    head = (tmp_path / "cc.ply").read_bytes()[:1000]
    assert b"CloudCompare" in head and b"property float scalar_" in head, head
    back = read_cloud(tmp_path / "cc.ply")
    np.testing.assert_allclose(back.points, points, rtol=0, atol=1e-5)  # float32
    # CloudCompare keeps normals compressed (quantised directions, a few milliradians)
    cosine = np.sum(back.normals * normals / np.linalg.norm(normals, axis=1)[:, None], axis=1)
    assert np.degrees(np.arccos(np.clip(cosine, -1, 1))).max() < 0.5


def test_deviation_csv_reads_back_as_a_cloud(tmp_path):
    from trueaxis.inspect.cloud import write_deviation_csv

    rng = np.random.default_rng(4)
    points = rng.uniform(-40, 40, (50, 3))
    deviation_um = rng.uniform(-30, 30, 50)
    write_deviation_csv(tmp_path / "dev.csv", points, deviation_um, ["cone"] * 25 + ["block_top"] * 25)
    lines = (tmp_path / "dev.csv").read_text().splitlines()
    assert lines[0] == "x_mm,y_mm,z_mm,deviation_um,surface" and lines[1].endswith(",cone")
    np.testing.assert_allclose(read_cloud(tmp_path / "dev.csv").points, points, rtol=0, atol=5e-7)
    np.testing.assert_allclose([float(line.split(",")[3]) for line in lines[1:]], deviation_um, atol=5e-5)


def test_deviation_csv_numbers_are_printfs_digits_without_minus_zero(tmp_path):
    """The compiled CSV writer against Python's '%.6f' / '%.4f' (C's printf): the same digits for every value that is
    not an exact binary tie, and no '-0.000000' for a negative value that rounds to zero; surface names as given."""
    from trueaxis.inspect.cloud import write_deviation_csv

    rng = np.random.default_rng(7)
    special = np.array([0.0, -0.0, 4e-7, -4e-7, 0.9999996, -0.9999996, 123456.7891234, -987.0000004, 1e-12, 41.5])
    points = np.column_stack([np.r_[special, rng.uniform(-500, 500, 400)],
                              np.r_[-special, rng.normal(0, 1e-3, 400)], np.r_[special[::-1], rng.uniform(-1, 1, 400)]])
    deviation_um = np.r_[special, rng.normal(0, 30, 400)]
    names = np.array(["cone", "block_top", "x"])[rng.integers(0, 3, len(points))]
    write_deviation_csv(tmp_path / "dev.csv", points, deviation_um, list(names))

    def printf(value, decimals):
        text = f"%.{decimals}f" % value
        return text[1:] if text.startswith("-") and float(text) == 0.0 else text

    lines = (tmp_path / "dev.csv").read_text().splitlines()[1:]
    expected = [",".join([printf(x, 6), printf(y, 6), printf(z, 6), printf(d, 4), name])
                for (x, y, z), d, name in zip(points, deviation_um, names)]
    assert lines == expected


def test_csv_header_units_are_read_into_mm_and_mixed_or_unknown_units_refused(tmp_path):
    """'X [in]' columns are inches (x 25.4 into mm), 'x_um' micrometres; x, y, z in different units, or a unit
    trueaxis does not know, are refused naming it (a declared unit was ignored: inch data read as mm)."""
    points = np.array([[1.0, 2.0, 3.0], [-0.5, 0.25, 1.5]])
    for header, scale in (("X [in],Y [in],Z [in]", 25.4), ("x_um,y_um,z_um", 1e-3), ("X (mm),Y (mm),Z (mm)", 1.0),
                          ("Name;X [cm];Y [cm];Z [cm]", 10.0)):
        delimiter = ";" if ";" in header else ","
        names = ["P1;", "P2;"] if header.startswith("Name") else ["", ""]
        text = header + "\n" + "".join(f"{n}{delimiter.join(str(v) for v in row)}\n" for n, row in zip(names, points))
        (tmp_path / "c.csv").write_text(text)
        np.testing.assert_allclose(read_cloud(tmp_path / "c.csv").points, points * scale, rtol=1e-15)
    (tmp_path / "c.csv").write_text("X [in],Y [mm],Z [mm]\n1,2,3\n")
    with pytest.raises(CloudError, match="different units"):
        read_cloud(tmp_path / "c.csv")
    (tmp_path / "c.csv").write_text("X [furlong],Y [furlong],Z [furlong]\n1,2,3\n")
    with pytest.raises(CloudError, match="'furlong'"):
        read_cloud(tmp_path / "c.csv")
    # a unit on x alone: y's and z's not said (it scaled all three by 25.4 without a word, a QA pass)
    (tmp_path / "c.csv").write_text("X [in],Y,Z\n1,2,3\n")
    with pytest.raises(CloudError, match=r"a unit for some coordinates only \(x in 'in'; y, z without\)"):
        read_cloud(tmp_path / "c.csv")


def test_numbers_with_a_thousands_separator_are_refused_for_what_they_are(tmp_path):
    """With ';', tab or spaces between the fields a ',' is read as the decimal comma; a number with both ',' and '.'
    (1,234.5 or 1.234,5) groups its digits, and was refused as "not a number" with its commas already turned to points
    ('1.234.5', a row the file does not have). Refused naming the row as written and the thousands separator; the
    same numbers without grouping are read."""
    for file, text in (("semi.csv", "x;y;z\n12.0;0.5;10.0\n1,234.5;0.5;10.0\n"),
                       ("euro.csv", "x;y;z\n12,0;0,5;10,0\n1.234,5;0,5;10,0\n"),
                       ("tab.txt", "12.0\t0.5\t10.0\n1,234.5\t0.5\t10.0\n")):
        (tmp_path / file).write_text(text)
        row = text.splitlines()[-1]
        message = refused(tmp_path / file, f"the row {row!r} has a number with both ',' and '.'")
        assert "thousands separator" in message and "1.234.5" not in message
    (tmp_path / "plain.csv").write_text("x;y;z\n12,0;0,5;10,0\n1234,5;0,5;10,0\n")
    np.testing.assert_array_equal(read_cloud(tmp_path / "plain.csv").points, [[12.0, 0.5, 10.0], [1234.5, 0.5, 10.0]])
