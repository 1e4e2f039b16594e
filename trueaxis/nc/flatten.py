"""What LinuxCNC evaluates before any motion: parameters, expressions, O-word control flow, M98 / M99.

:func:`flatten_program` runs a program's macro layer the way LinuxCNC's rs274ngc interpreter does and writes the
program *flat*: every executed block with plain numbers in place of ``#1``, ``#<name>`` and ``[...]``, loops unrolled,
subroutine bodies written where they are called, assignments and O-word lines gone. The G-code reader and the post
then see plain blocks; a line map names the source line of every flat line, so messages point at the user's text.

What is evaluated (LinuxCNC's G-code manual, "Parameters", "Expressions", "O Codes"; checked against ``rs274``):

- numbered parameters ``#1`` .. ``#5160`` (unset ones read 0, as ``rs274`` without a parameter file reads them),
  named parameters ``#<name>`` (local to the subroutine that sets them) and ``#<_name>`` (global); reading an unset
  named parameter is refused, as ``rs274`` refuses it. Parameters that hold the controller's state (``#5161`` and
  above: G28 / G30 / G92 / work offsets, tool, position; ``#<_x>``, ``#<_metric>`` and the other predefined names) are
  refused: their values depend on the interpreter state, which this pre-pass does not keep;
- assignments take effect after the whole line is read (``#1=5 G0 X#1`` moves to the old ``#1``);
- expressions with ``+ - * / MOD **``, ``EQ NE GT GE LT LE`` (EQ / NE within 0.0001 as the installed ``rs274``),
  ``AND OR XOR``, LinuxCNC's precedence (``**`` > ``* / MOD`` > ``+ -`` > comparisons > logic; left to right within one
  level), and the functions ``ABS ACOS ASIN ATAN[a]/[b] COS EXP FIX FUP LN ROUND SIN SQRT TAN EXISTS`` (angles in
  degrees);
- O-words: ``sub / endsub / return / call`` with up to 30 arguments in ``#1``..``#30`` (the caller's restored on
  return), ``if / elseif / else / endif``, ``while / endwhile``, ``do / while``, ``repeat / endrepeat``,
  ``break / continue``; Fanuc ``M98 P<n> [L<count>]`` calling ``O<n>`` ... ``M99`` in the same file.

Refused with the reason: subroutines not in the file (LinuxCNC would search its subroutine path), ``M99`` in the main
program (an endless repeat), more than :data:`MAX_FLAT_BLOCKS` executed blocks (a loop that does not end).
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass

from .grammar import NUMBER

__all__ = ["FlatProgram", "flatten_program", "needs_flattening", "MAX_FLAT_BLOCKS"]

# A program that executes more blocks than this is refused (an endless loop, or one no machine runs).
MAX_FLAT_BLOCKS = 2_000_000
# EQ / NE / LE / GE tolerance of the installed rs274 (LinuxCNC 2.9.0~pre1)
TOLERANCE_EQUAL = 1e-4
# Numbered parameters a program may use; #5161 and above hold the controller's state
FIRST_STATE_PARAMETER = 5161
LAST_PARAMETER = 5601
# Predefined named parameters (LinuxCNC's "predefined named parameters"): the interpreter's state, not evaluated here
_SYSTEM_NAMES = re.compile(
    r"_(?:" + "|".join((
        "vmajor vminor line motion_mode plane ccomp metric imperial absolute incremental inverse_time units_per_minute "
        "units_per_rev coord_system tool_offset retract_r_plane retract_old_z spindle_rpm_mode spindle_css_mode "
        "ijk_absolute_mode lathe_diameter_mode lathe_radius_mode spindle_on spindle_cw mist flood speed_override "
        "feed_override adaptive_feed feed_hold feed rpm current_tool current_pocket selected_tool selected_pocket "
        "value value_returned task call_level remap_level").split())
    + r"|[xyzabcuvw]|abs_[xyzabcuvw]|ini\[.*\]|hal\[.*\])$"
)

# A quick look decides: without '#', '[', an O-word with a keyword or M98 / M99 there is nothing to evaluate. (Each
# pattern starts with a literal letter, which the regular-expression engine finds fast; an alternation would try
# every branch at every character: 60 ms for 100,000 lines against 2 ms.)
_FEATURE_PATTERNS = tuple(re.compile(p) for p in (
    r"O[ \t]*(?:<|[0-9]+[ \t]*[A-Za-z])", r"o[ \t]*(?:<|[0-9]+[ \t]*[A-Za-z])",
    r"M[ \t]*0*9[ \t]*[89](?![ \t]*[0-9.])", r"m[ \t]*0*9[ \t]*[89](?![ \t]*[0-9.])",
))


class _Features:
    """``search(text)``: truthy when the text may need flattening."""

    @staticmethod
    def search(text):
        return "#" in text or "[" in text or any(_found(p, text) for p in _FEATURE_PATTERNS) or None


def _found(pattern, text) -> bool:
    """Does ``pattern`` (starting with a literal letter) match somewhere in ``text``? Tried only where its letter
    occurs (``str.find`` runs at memory speed; ``search`` steps through every character: 0.3 s on a 75 MB program
    whose comments have an 'm' near the top and none after)."""
    letter = pattern.pattern[0]
    at = text.find(letter)
    while at >= 0:
        if pattern.match(text, at):
            return True
        at = text.find(letter, at + 1)
    return False


_FEATURES = _Features()
_KEYWORDS = ("endsub", "endwhile", "endrepeat", "endif", "elseif", "else", "sub", "call", "if", "while", "do",
             "repeat", "return", "break", "continue")
_OLINE = re.compile(r"^(/)?(?:n[0-9.]+)?o(<[^>]*>|[0-9]+)(" + "|".join(_KEYWORDS) + r")?(.*)$")
_END = re.compile(r"m0*(?:2|30)(?![0-9.])")
_NUMBER = re.compile(NUMBER)
_FUNCS = ("abs", "acos", "asin", "atan", "cos", "exists", "exp", "fix", "fup", "ln", "round", "sin", "sqrt", "tan")
# binary operators, longest spelling first, with LinuxCNC's precedence
_BINOPS = (("**", 6), ("*", 5), ("/", 5), ("mod", 5), ("+", 4), ("-", 4), ("eq", 3), ("ne", 3), ("gt", 3),
           ("ge", 3), ("lt", 3), ("le", 3), ("and", 2), ("or", 2), ("xor", 2))


def _round(v):
    return float(int(v + (-0.5 if v < 0 else 0.5)))


_FUNCTION = {"abs": abs, "acos": lambda v: math.degrees(math.acos(v)), "asin": lambda v: math.degrees(math.asin(v)),
             "cos": lambda v: math.cos(math.radians(v)), "sin": lambda v: math.sin(math.radians(v)),
             "tan": lambda v: math.tan(math.radians(v)), "exp": math.exp, "fix": lambda v: float(math.floor(v)),
             "fup": lambda v: float(math.ceil(v)), "ln": math.log, "round": _round, "sqrt": math.sqrt}


def _c_value(f, *args):
    """f(*args) as C computes it: NaN where Python raises ValueError (fmod by 0, sin of inf, floor of NaN), inf
    where it raises OverflowError (exp, pow)."""
    try:
        return float(f(*args))
    except ValueError:
        return math.nan
    except OverflowError:
        return math.inf


class FlattenError(Exception):
    """A macro the pre-pass refuses: ``line`` is the 1-based source line."""

    def __init__(self, line: int, reason: str):
        self.line, self.reason = line, reason
        super().__init__(f"line {line}: {reason}")


@dataclass
class FlatProgram:
    """A flattened program: ``text`` (plain blocks) and ``source_line`` (one 1-based source line per flat line)."""

    text: str
    source_line: list


def needs_flattening(text: str) -> bool:
    """True when ``text`` may have parameters, expressions, O-word control flow or M98 / M99 (a few fast scans)."""
    return _FEATURES.search(text) is not None


def format_value(v: float) -> str:
    """A flat word's number: at most 6 decimals (1 nm, or 25 nm in inches), no trailing zeros, never "-0"."""
    s = f"{v:.6f}".rstrip("0").rstrip(".")
    return "0" if s in ("-0", "", "+0") else s


def _code_and_comments(raw: str):
    """(code, comments) of one line as rs274 reads it: spaces and tabs dropped, lower case outside comments."""
    code, comments, i, n = [], [], 0, len(raw)
    while i < n:
        c = raw[i]
        if c == "(":
            j = raw.find(")", i)
            j = n - 1 if j < 0 else j
            comments.append(raw[i:j + 1])
            i = j + 1
        elif c == ";":
            comments.append(raw[i:].rstrip("\r\n"))
            break
        else:
            if c not in " \t\r\n":
                code.append(c.lower())
            i += 1
    return "".join(code), comments


def _ending(raw: str) -> str:
    """The line ending of ``raw`` (\\n when it has none: the last line), kept on the flat line."""
    return raw[len(raw.rstrip("\r\n")):] or "\n"


class _Frame:
    def __init__(self, return_to, saved, line):
        self.return_to, self.saved, self.line = return_to, saved, line
        self.named: dict = {}
        self.repeat: dict = {}


class _Flattener:
    def __init__(self, lines, params):
        self.lines = lines
        self.params = {int(k): float(v) for k, v in (params or {}).items()}
        self.globals: dict = {}
        self.frames = [_Frame(None, None, 0)]
        self.code = [None] * len(lines)  # cached (code, comments)
        self.index_olines()

    # -- reading ------------------------------------------------------------------------------------------------
    def line_code(self, k):
        if self.code[k] is None:
            self.code[k] = _code_and_comments(self.lines[k])
        return self.code[k]

    def index_olines(self):
        """O-word lines: k -> (label, keyword, rest); subroutine starts; the do-loops' closing while lines."""
        self.olines = {}
        self.subs = {}
        self.fanuc = {}  # O<number> without keyword -> line (Fanuc subprogram start, for M98)
        open_do = {}
        for k, raw in enumerate(self.lines):
            s = raw.lstrip()
            if not s or s[0] not in "oOnN/":
                continue
            code, _ = self.line_code(k)
            m = _OLINE.match(code)
            if not m:
                continue
            label = m.group(2)
            if not label.startswith("<"):
                label = str(int(label))
            kw, rest = m.group(3), m.group(4)
            if kw is None:
                if not rest or rest[0] == "(":
                    self.fanuc.setdefault(label, k)
                continue
            if kw == "sub":
                self.subs[label] = k
            elif kw == "do":
                open_do[label] = k
            elif kw == "while" and label in open_do:
                kw = "dowhile"
                del open_do[label]
            self.olines[k] = (label, kw, rest)

    def find(self, start, label, keywords, step=1):
        k = start
        while 0 <= k < len(self.lines):
            o = self.olines.get(k)
            if o is not None and o[0] == label and o[1] in keywords:
                return k
            k += step
        return None

    # -- values -------------------------------------------------------------------------------------------------
    def err(self, reason):
        raise FlattenError(self.at + 1, reason)

    def get_named(self, name):
        if name.startswith("_"):
            if name in self.globals:
                return self.globals[name]
            if _SYSTEM_NAMES.match(name):
                self.err(f"predefined parameter #<{name}> holds the controller's state, which is not evaluated here")
        else:
            v = self.frames[-1].named.get(name)
            if v is not None:
                return v
        self.err(f"named parameter #<{name}> is not defined")

    def get_number(self, n):
        if not 1 <= n <= LAST_PARAMETER:
            self.err(f"parameter number #{n} out of range (1 .. {LAST_PARAMETER})")
        if n >= FIRST_STATE_PARAMETER:
            self.err(f"parameter #{n} holds the controller's state (reference points, offsets, tool, position), "
                     "which is not evaluated here")
        return self.params.get(n, 0.0)

    def param_ref(self, s, i):
        """(key, i): s[i] == '#'; key an int or a name."""
        i += 1
        if i < len(s) and s[i] == "<":
            j = s.find(">", i)
            if j < 0:
                self.err("named parameter not closed with '>'")
            name = s[i + 1:j]
            if not name:
                self.err("named parameter with no name")
            return name, j + 1
        v, i = self.real_value(s, i)
        n = round(v)
        if abs(v - n) > 1e-4:
            self.err(f"parameter number #{v:g} is not an integer")
        return int(n), i

    def param_value(self, s, i):
        key, i = self.param_ref(s, i)
        return (self.get_named(key) if isinstance(key, str) else self.get_number(key)), i

    def real_value(self, s, i):
        if i >= len(s):
            self.err("a value is missing at the end of the block")
        c = s[i]
        if c == "[":
            return self.expression(s, i)
        if c == "#":
            return self.param_value(s, i)
        if c in "+-" and i + 1 < len(s) and s[i + 1] in "#[abcdefghijklmnopqrstuvwxyz":
            v, j = self.real_value(s, i + 1)
            return (-v if c == "-" else v), j
        if c.isalpha():
            for f in _FUNCS:
                if s.startswith(f, i):
                    return self.function(f, s, i + len(f))
            self.err(f"unknown word or function at '{s[i:i + 8]}'")
        m = _NUMBER.match(s, i)
        if not m:
            self.err(f"bad number at '{s[i:i + 8]}'")
        return float(m.group()), m.end()

    def function(self, f, s, i):
        if i >= len(s) or s[i] != "[":
            self.err(f"{f.upper()} needs its argument in [ ]")
        if f == "exists":
            j = s.find("]", i)
            arg = s[i + 1:j] if j > 0 else ""
            if not (arg.startswith("#<") and arg.endswith(">")):
                self.err("EXISTS needs a named parameter: EXISTS[#<name>]")
            name = arg[2:-1]
            found = name in self.globals if name.startswith("_") else name in self.frames[-1].named
            return (1.0 if found else 0.0), j + 1
        v, i = self.expression(s, i)
        if f == "atan":
            if i >= len(s) or s[i] != "/":
                self.err("ATAN needs two arguments: ATAN[y]/[x]")
            w, i = self.expression(s, i + 1)
            return math.degrees(math.atan2(v, w)), i
        # rs274's domain checks (a NaN passes them, as in C); then the value as C's libm gives it: NaN or inf where
        # Python raises
        if f in ("acos", "asin") and (v < -1.0 or v > 1.0):
            self.err(f"argument to {f.upper()} out of range [-1, 1]: {v:g}")
        if f == "sqrt" and v < 0:
            self.err(f"negative argument to SQRT: {v:g}")
        if f == "ln" and v <= 0:
            self.err(f"zero or negative argument to LN: {v:g}")
        return _c_value(_FUNCTION[f], v), i

    def expression(self, s, i):
        """Value of the bracketed expression at s[i] == '[' and the index after its ']'."""
        values, ops = [], []
        v, i = self.real_value(s, i + 1)
        values.append(v)
        while True:
            if i >= len(s):
                self.err("expression not closed with ']'")
            if s[i] == "]":
                i += 1
                break
            for name, prec in _BINOPS:
                if s.startswith(name, i):
                    break
            else:
                self.err(f"unknown operator at '{s[i:i + 8]}'")
            i += len(name)
            # left to right within one precedence level: reduce while the stacked operator binds as tightly
            while ops and ops[-1][1] >= prec:
                self.reduce(values, ops)
            ops.append((name, prec))
            v, i = self.real_value(s, i)
            values.append(v)
        while ops:
            self.reduce(values, ops)
        if values[0] != values[0]:
            self.err("calculation resulted in 'not a number' (NaN)")
        return values[0], i

    def reduce(self, values, ops):
        """Apply the stacked operator to the two last values, as rs274's execute_binary does (C arithmetic: inf and
        NaN carry on; the word that finally gets such a value is refused)."""
        name, _ = ops.pop()
        b = values.pop()
        a = values.pop()
        if name == "/":
            if b == 0.0:
                self.err("division by zero")
            r = a / b
        elif name == "mod":
            r = _c_value(math.fmod, a, b)
            r = r + abs(b) if r < 0 else r
        elif name == "**":
            if a < 0 and (b != b or (math.isfinite(b) and math.floor(b) != b)):
                self.err("negative number raised to a non-integer power")
            r = _c_value(math.pow, a, b)
        elif name == "*":
            r = a * b
        elif name == "+":
            r = a + b
        elif name == "-":
            r = a - b
        elif name == "and":
            r = 0.0 if a == 0.0 or b == 0.0 else 1.0
        elif name == "or":
            r = 1.0 if a != 0.0 or b != 0.0 else 0.0
        elif name == "xor":
            r = 1.0 if (a == 0.0) != (b == 0.0) else 0.0
        elif name == "eq":
            r = 1.0 if abs(a - b) < TOLERANCE_EQUAL else 0.0
        elif name == "ne":
            r = 1.0 if abs(a - b) >= TOLERANCE_EQUAL else 0.0
        elif name == "le":  # the installed rs274 compares LE / GE exactly (newer LinuxCNC within its tolerance)
            r = 1.0 if a <= b else 0.0
        elif name == "ge":
            r = 1.0 if a >= b else 0.0
        elif name == "gt":
            r = 1.0 if a > b else 0.0
        else:
            r = 1.0 if a < b else 0.0
        values.append(r)

    def assign(self, key, value):
        if isinstance(key, str):
            if key.startswith("_"):
                if _SYSTEM_NAMES.match(key):
                    self.err(f"predefined parameter #<{key}> is read-only")
                self.globals[key] = value
            else:
                self.frames[-1].named[key] = value
        else:
            if not 1 <= key <= LAST_PARAMETER:
                self.err(f"parameter number #{key} out of range (1 .. {LAST_PARAMETER})")
            if key >= FIRST_STATE_PARAMETER:
                self.err(f"parameter #{key} holds the controller's state; setting it here is not supported")
            self.params[key] = value

    # -- one block ------------------------------------------------------------------------------------------------
    def block(self, k):
        """The flat text of ordinary line k (None: nothing to write), and its M98 / M99 (or None)."""
        raw = self.lines[k]
        code, comments = self.line_code(k)
        if "#" not in code and "[" not in code and not re.search(r"m0*9[89](?![0-9.])", code):
            return raw, None
        words, sets, call = [], [], None
        i, n = 0, len(code)
        if code.startswith("/"):
            words.append("/")
            i = 1
        while i < n:
            c = code[i]
            if c == "#":
                key, i = self.param_ref(code, i)
                if i >= n or code[i] != "=":
                    self.err("a parameter in a block must be set with '=' (use it as a word's value)")
                v, i = self.real_value(code, i + 1)
                sets.append((key, v))
            elif c.isalpha():
                if c == "n":
                    m = re.compile(r"[0-9]+\.?[0-9]*").match(code, i + 1)
                    if m is None:
                        self.err("a line number (N word) must be an unsigned number, not an expression")
                    words.append("N" + m.group())
                    i = m.end()
                    continue
                v, i = self.real_value(code, i + 1)
                if not math.isfinite(v):
                    self.err(f"number out of range: the value of {c.upper()} is not a finite number ({v})")
                if c in "gm":
                    v10 = round(v * 10)
                    if abs(v * 10 - v10) > 1e-3:
                        self.err(f"{c.upper()}{v:g} is not a code (one decimal at most)")
                    v = v10 / 10
                words.append(c.upper() + format_value(v))
            else:
                self.err(f"unexpected character {c!r}")
        for key, v in sets:
            self.assign(key, v)
        m_calls = [w for w in words if w in ("M98", "M99")]
        if m_calls:
            if "M98" in m_calls:
                p = next((w[1:] for w in words if w[0] == "P"), None)
                if p is None:
                    self.err("M98 needs a P word: the program number to call")
                count = next((w[1:] for w in words if w[0] == "L"), "1")
                rest = [w for w in words if w[0] not in "MPLN/"]
                if rest:
                    self.err("M98 with other words in the block is not supported here: put them on their own line")
                call = ("M98", str(int(float(p))), int(float(count)))
            else:
                rest = [w for w in words if w[0] not in "MN/"]
                if rest or len(words) - (1 if words[0][0] in "N/" else 0) > 1:
                    self.err("M99 with other words in the block is not supported here: put them on their own line")
                call = ("M99",)
            return None, call
        if not words or words == ["/"]:
            return ("".join(comments) + _ending(raw)) if comments else None, None
        return " ".join(words + comments) + _ending(raw), None

    # -- the run ------------------------------------------------------------------------------------------------
    def run(self):
        out, src = [], []
        k, n = 0, len(self.lines)
        executed = percents = 0
        while k < n:
            self.at = k
            executed += 1
            if executed > MAX_FLAT_BLOCKS:
                self.err(f"more than {MAX_FLAT_BLOCKS} blocks executed: a loop that does not end?")
            o = self.olines.get(k)
            if o is not None:
                k = self.control(k, o)
                continue
            if k in self.fanuc_called:
                # a Fanuc subprogram's start reached in the program's flow: its body runs only through M98
                end = self.fanuc_end(k)
                k = end + 1
                continue
            text, call = self.block(k)
            if call is not None:
                if call[0] == "M98":
                    start = self.fanuc.get(call[1])
                    if start is None:
                        self.err(f"M98 P{call[1]}: program O{call[1]} is not in this file")
                    if call[2] < 1:
                        k += 1
                        continue
                    self.fanuc_end(start)
                    frame = _Frame(k + 1, None, start)
                    frame.repeat["m98"] = call[2]
                    self.frames.append(frame)
                    k = start + 1
                    continue
                if len(self.frames) == 1 or self.frames[-1].saved is not None:
                    self.err("M99 in the main program repeats it without end (Fanuc) or ends it: not supported")
                frame = self.frames[-1]
                frame.repeat["m98"] -= 1
                if frame.repeat["m98"] > 0:
                    k = frame.line + 1
                    continue
                self.frames.pop()
                k = frame.return_to
                continue
            if text is not None:
                out.append(text if text.endswith(("\n", "\r")) else text + "\n")
                src.append(k + 1)
            code = self.line_code(k)[0]
            if self.lines[k].lstrip()[:1] == "%":  # (as the reader tells a '%' line)
                percents += 1
                if percents == 2:
                    break  # the closing '%': what follows is not read
            elif len(self.frames) == 1 and _END.search(code):
                break  # program end: what follows is not executed
            k += 1
        if src == list(range(1, len(src) + 1)) and all(a is b for a, b in zip(out, self.lines)):
            return None  # '#' or '[' only in comments: nothing evaluated, every line as it is
        if percents == 1 and k < n:  # ended by M2 / M30 in a program that opened with '%': its closing '%' kept
            closing = self.closing_percent(k + 1)
            if closing is not None:
                out.append(self.lines[closing])  # (as it is: without a line ending, it is the file's last)
                src.append(closing + 1)
        if out and not self.lines[-1].endswith(("\n", "\r")) and out[-1].endswith("\n") and \
                self.lines[src[-1] - 1] is self.lines[-1]:
            out[-1] = out[-1][:-1]
        return FlatProgram("".join(out), src)

    def closing_percent(self, start):
        """The index of the first '%' line from line ``start`` on (None: none). The lines between the program's end
        and it are not executed, and not written: the flat program is what runs."""
        for k in range(start, len(self.lines)):
            if self.lines[k].lstrip()[:1] == "%":
                return k
        return None

    @property
    def fanuc_called(self):
        if not hasattr(self, "_fanuc_called"):
            called = set()
            for k, raw in enumerate(self.lines):
                if "98" in raw:
                    code = self.line_code(k)[0]
                    for m in re.finditer(r"m0*98p([0-9]+)", code):
                        if m.group(1).lstrip("0") in self.fanuc or str(int(m.group(1))) in self.fanuc:
                            called.add(self.fanuc[str(int(m.group(1)))])
            self._fanuc_called = called
        return self._fanuc_called

    def fanuc_end(self, start):
        for k in range(start + 1, len(self.lines)):
            if re.search(r"m0*99(?![0-9.])", self.line_code(k)[0]):
                return k
        self.at = start
        self.err("Fanuc subprogram without M99")

    def call(self, k, label, rest):
        """o<label> call [args]: the arguments into #1..#30 (the caller's saved), on to the subroutine's body."""
        start = self.subs.get(label)
        if start is None:
            self.err(f"subroutine o{label} is not in this file (LinuxCNC would look for a file of that name "
                     "in its subroutine path)")
        args, i = [], 0
        while i < len(rest):
            if rest[i] == "(":
                break
            if rest[i] != "[":
                self.err("call arguments must be in [ ]")
            v, i = self.expression(rest, i)
            args.append(v)
        if len(args) > 30:
            self.err("more than 30 call arguments")
        if len(self.frames) > 200:
            self.err("subroutine calls nested more than 200 deep (a recursion that does not end?)")
        saved = {j: self.params.get(j, 0.0) for j in range(1, 31)}
        for j in range(1, 31):
            self.params[j] = args[j - 1] if j <= len(args) else 0.0
        self.frames.append(_Frame(k + 1, saved, start))
        return start + 1

    def sub_return(self, label, kw, rest):
        """o<label> endsub / return [value]: the caller's #1..#30 restored, back after the call."""
        if len(self.frames) == 1:
            if kw == "endsub":
                self.err(f"o{label} endsub outside a subroutine")
            self.err(f"o{label} return outside a subroutine")
        rest_code = rest.split("(", 1)[0]
        if rest_code.startswith("["):
            self.globals["_value"], _ = self.expression(rest_code, 0)
        f = self.frames.pop()
        if f.saved is None:
            self.err("o-word return inside an M98 subprogram")
        self.params.update(f.saved)
        return f.return_to

    def control(self, k, o):
        label, kw, rest = o
        frame = self.frames[-1]
        if kw == "sub":
            end = self.find(k + 1, label, ("endsub",))
            if end is None:
                self.err(f"o{label} sub without o{label} endsub")
            return end + 1
        if kw == "call":
            return self.call(k, label, rest)
        if kw in ("endsub", "return"):
            return self.sub_return(label, kw, rest)
        cond = None
        if kw in ("if", "elseif", "while", "dowhile", "repeat"):
            rest_code = rest.split("(", 1)[0]
            if not rest_code.startswith("["):
                self.err(f"o{label} {kw if kw != 'dowhile' else 'while'} needs a condition in [ ]")
            cond, _ = self.expression(rest_code, 0)
        if kw == "elseif":  # reached after a taken branch: on to the endif
            end = self.find(k + 1, label, ("endif",))
            if end is None:
                self.err(f"o{label} elseif without o{label} endif")
            return end + 1
        if kw == "if":
            while cond == 0.0:
                nxt = self.find(k + 1, label, ("elseif", "else", "endif"))
                if nxt is None:
                    self.err(f"o{label} if without o{label} endif")
                k = self.at = nxt
                _, kw2, rest2 = self.olines[nxt]
                if kw2 != "elseif":
                    return nxt + 1
                cond, _ = self.expression(rest2.split("(", 1)[0], 0)
            return k + 1
        if kw == "else":  # reached after a taken branch
            end = self.find(k + 1, label, ("endif",))
            if end is None:
                self.err(f"o{label} else without o{label} endif")
            return end + 1
        if kw == "endif":
            return k + 1
        if kw == "while":
            if cond != 0.0:
                return k + 1
            end = self.find(k + 1, label, ("endwhile",))
            if end is None:
                self.err(f"o{label} while without o{label} endwhile")
            return end + 1
        if kw == "endwhile":
            head = self.find(k - 1, label, ("while",), -1)
            if head is None:
                self.err(f"o{label} endwhile without o{label} while")
            return head
        if kw == "do":
            return k + 1
        if kw == "dowhile":
            if cond != 0.0:
                return self.find(k - 1, label, ("do",), -1) + 1
            return k + 1
        if kw == "repeat":
            count = int(cond) if cond > 0 else 0
            frame.repeat[k] = count
            if count <= 0:
                end = self.find(k + 1, label, ("endrepeat",))
                if end is None:
                    self.err(f"o{label} repeat without o{label} endrepeat")
                return end + 1
            return k + 1
        if kw == "endrepeat":
            head = self.find(k - 1, label, ("repeat",), -1)
            if head is None:
                self.err(f"o{label} endrepeat without o{label} repeat")
            frame.repeat[head] = frame.repeat.get(head, 1) - 1
            return head + 1 if frame.repeat[head] > 0 else k + 1
        if kw == "break":
            end = self.find(k + 1, label, ("endwhile", "endrepeat", "dowhile"))
            if end is None:
                self.err(f"o{label} break outside a loop")
            return end + 1
        if kw == "continue":
            end = self.find(k + 1, label, ("endwhile", "endrepeat", "dowhile"))
            if end is None:
                self.err(f"o{label} continue outside a loop")
            return end
        self.err(f"o-word '{kw}' is not supported")


def flatten_program(text: str, lines: list | None = None, params: dict | None = None) -> FlatProgram | None:
    """The program with its macro layer evaluated (see the module docstring), or None when it has none (fast path:
    the text is then read as it is). ``lines``: the text split into lines with their endings (``split_lines``);
    ``params``: numbered parameter values (a LinuxCNC .var file's), unset ones read 0.

    Raises :class:`FlattenError` (1-based source line, reason) for what LinuxCNC refuses or this pass does not do."""
    if _FEATURES.search(text) is None:
        return None
    if lines is None:
        lines = text.splitlines(keepends=True)
    return _Flattener(lines, params).run()


# The lines a program starts with that stay first: its '%' (LinuxCNC reads one only as the first line: "Bad character
# '%' used" elsewhere) and its program number (O1234, O0000(NAME)). The flat program's note and the post's header go
# after them.
_START_LINE = re.compile(r"^[ \t]*(?:%.*|[Oo][ \t]*[0-9]+[ \t]*(?:[(;].*)?)$")


def program_start(text: str, most: int = 3) -> int:
    """The length in characters of ``text``'s leading '%' and program number lines (at most ``most`` lines, each
    ended by a line ending; one '%' at most: a second one ends the program, and what goes after the start must not
    go after it; 0: none)."""
    pos, percent = 0, False
    for line in text[:4096].splitlines(keepends=True)[:most]:
        if not (_START_LINE.match(line.rstrip("\r\n")) and line.endswith(("\n", "\r"))):
            break
        if line.lstrip(" \t").startswith("%"):
            if percent:
                break
            percent = True
        pos += len(line)
    return pos


FLAT_NOTE = ("(flattened by trueaxis: parameters, expressions, O-word control flow and M98 subprograms evaluated as "
             "LinuxCNC does)")


def read_flat(text: str, source: str, passthrough: bool, split, interpret):
    """Read ``text`` through the pre-pass, rs274's block checks (:mod:`.check`) and ``interpret`` (text -> Program).

    A program with macros is flattened first; its Program then reads the flat text (its first line after a leading
    '%' and program number a comment saying so), ``Program.source_line`` maps each flat line to the source line, and every message names the source line.
    With ``passthrough`` a macro layer the pre-pass refuses is left to the reader, which passes such blocks through.
    """
    from .check import check_blocks
    from .gcode import GcodeError

    flat = None
    if _FEATURES.search(text) is not None:
        lines = split(text)  # (only a program with macros is split here: a plain one goes to the reader as it is)
        try:
            flat = _Flattener(lines, None).run()
        except FlattenError as exc:
            if not passthrough:
                raise GcodeError(source, exc.line, exc.reason) from None
            flat = None
    if flat is None:  # nothing to evaluate (or refused and passed through)
        check_blocks(text, source, passthrough, None)
        return interpret(text)
    at = program_start(flat.text)  # the note after the leading '%' and program number
    n_start = len(flat.text[:at].splitlines())
    flat_text = flat.text[:at] + FLAT_NOTE + _ending(lines[0]) + flat.text[at:]
    line_map = flat.source_line[:n_start] + [flat.source_line[n_start - 1] if n_start else 1] + \
        flat.source_line[n_start:]
    check_blocks(flat_text, source, passthrough, line_map)
    try:
        prog = interpret(flat_text)
    except GcodeError as exc:
        line = line_map[min(max(exc.line_no, 1), len(line_map)) - 1]
        raise GcodeError(source, line, exc.reason) from None
    import numpy as np

    prog.source_line = np.asarray(line_map + [line_map[-1]], np.int32)
    prog.unsupported = [(line_map[min(ln, len(line_map)) - 1], r) for ln, r in prog.unsupported]
    prefix = re.escape(source) + r":([0-9]+):"
    prog.warnings = [re.sub("^" + prefix, lambda m: f"{source}:{line_map[min(int(m.group(1)), len(line_map)) - 1]}:",
                            w) for w in prog.warnings]
    # the setup's sources ("file:line (G10 L2)") and first uses (the header's and the report's provenance) too
    at_line = re.compile("^" + re.escape(source) + r":([0-9]+)(?![0-9])")
    for used in prog.setup_used:
        if isinstance(used.get("source"), str):
            used["source"] = at_line.sub(
                lambda m: f"{source}:{line_map[min(int(m.group(1)), len(line_map)) - 1]}", used["source"])
        if isinstance(used.get("first_line"), int):
            used["first_line"] = line_map[min(max(used["first_line"], 1), len(line_map)) - 1]
    first = next((n for n, ln in enumerate(lines, 1) if _FEATURES.search(ln)), 1)  # the first line flattened
    prog.warnings.insert(0, f"{source}:{first}: flattened: parameters, expressions and O-word / M98 control flow "
                            f"evaluated ({len(flat.source_line)} flat blocks); the output is the flat program")
    return prog
