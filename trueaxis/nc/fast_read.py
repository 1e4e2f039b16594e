"""A compiled pre-scan for the G-code reader's fast path (:mod:`trueaxis.nc.gcode`).

The reader's fast path takes plain blocks ("N300G1X4.6526Z-.0007", "X1 Y2 F300") that its regular expression
``_FAST`` matches: optional leading blanks, an optional ``N`` number, an optional ``G0``..``G3`` (also
``G00``..``G03``), then the words X Y Z A B C I J K R F in this order, each at most once, upper case, blanks and tabs
between. Matching that expression and calling ``float()`` on the values is a large share of the time the reader
spends on such lines. This module does both for all lines of a program at once, in compiled code:

- :func:`line_starts` splits the program's bytes at ``\\n``, ``\\r\\n`` and a lone ``\\r``, as ``split_lines`` does;
- :func:`scan_lines` decides for every line whether it matches ``_FAST`` exactly, and reads the G digit and the
  values of X..F.

Values are read exactly as Python's ``float()`` reads them, or not at all: a decimal whose digits make an integer
mantissa below 2**53 with at most 22 digits after the point is ``mantissa / 10**digits`` -- both numbers exact in a
double, so the one correctly rounded division is the correctly rounded value of the decimal (Clinger's fast path),
which is what ``float()`` returns. Any other number (more significant digits than that) marks its line
:data:`LINE_SLOW`, and the reader handles that line with the regular expression and ``float()`` as before.

Only ASCII text is scanned (the reader skips the pre-scan otherwise).
"""

from __future__ import annotations

from ..compiled import numba  # numba, or the kernels compiled ahead of time (see ..compiled)
import numpy as np

__all__ = ["LINE_NO_MATCH", "LINE_NO_MOTION", "LINE_FAST", "LINE_SLOW", "WORDS", "line_starts", "scan_lines",
           "scan_text", "number_style", "next_check_candidate", "ijkr_after_linear"]

# per-line status
LINE_NO_MATCH = 0  # the line is not a _FAST block (general path)
LINE_NO_MOTION = 1  # matches _FAST but has no G0-G3 and no axis word (the reader's general path too)
LINE_FAST = 2  # matches, values read here (exactly as float() would)
LINE_SLOW = 3  # matches, but a value has too many digits for the exact fast conversion: regex and float() in Python

WORDS = "XYZABCIJKRF"
_WORD_CODES = np.array([ord(c) for c in WORDS], np.uint8)
# 10**k, k = 0..22: all exact in a double
_POW10 = np.array([1e0, 1e1, 1e2, 1e3, 1e4, 1e5, 1e6, 1e7, 1e8, 1e9, 1e10, 1e11, 1e12, 1e13, 1e14, 1e15, 1e16, 1e17,
                   1e18, 1e19, 1e20, 1e21, 1e22], np.float64)
_TWO53 = 2**53
_MAX_INT_DIGITS = 9  # _FAST's [0-9]{1,9}

_CR, _LF, _SP, _TAB = 13, 10, 32, 9
_DOT, _PLUS, _MINUS = 46, 43, 45
_D0, _D3, _D9 = 48, 51, 57
_N, _G = 78, 71


@numba.njit(cache=True, nogil=True)
def line_starts(buf):
    """Start offsets of the lines of ``buf`` (uint8) and, last, ``len(buf)``: lines end at \\n, \\r\\n or a lone \\r.

    Line ``i`` is ``buf[starts[i]:starts[i + 1]]`` with its ending.
    """
    n = buf.shape[0]
    count = 0
    i = 0
    while i < n:
        c = buf[i]
        if c == _LF:
            count += 1
        elif c == _CR:
            if i + 1 < n and buf[i + 1] == _LF:
                i += 1
            count += 1
        i += 1
    if n > 0 and buf[n - 1] != _LF and buf[n - 1] != _CR:
        count += 1
    out = np.empty(count + 1, np.int64)
    k = 0
    out[0] = 0
    i = 0
    while i < n:
        c = buf[i]
        if c == _LF:
            k += 1
            out[k] = i + 1
        elif c == _CR:
            if i + 1 < n and buf[i + 1] == _LF:
                i += 1
            k += 1
            out[k] = i + 1
        i += 1
    out[count] = n
    return out


@numba.njit(cache=True, nogil=True)
def _scan_line(buf, s, e, vals, row):
    """Match buf[s:e] (one line, with its ending) against _FAST; fill vals[row] (NaN = absent) and return
    (status, g) with g = -1 when the line has no G word."""
    # the ending: _FAST's \r?\n?\Z (line_starts leaves no other \r or \n inside a line)
    if e > s and buf[e - 1] == _LF:
        e -= 1
    if e > s and buf[e - 1] == _CR:
        e -= 1
    for k in range(11):
        vals[row, k] = np.nan
    p = s
    while p < e and (buf[p] == _SP or buf[p] == _TAB):
        p += 1
    # N[0-9]+[ \t]*
    if p < e and buf[p] == _N:
        p += 1
        if p >= e or buf[p] < _D0 or buf[p] > _D9:
            return LINE_NO_MATCH, -1
        while p < e and _D0 <= buf[p] <= _D9:
            p += 1
        while p < e and (buf[p] == _SP or buf[p] == _TAB):
            p += 1
    # G0?([0-3])(?![0-9.])[ \t]*
    g = -1
    if p < e and buf[p] == _G:
        c1 = buf[p + 1] if p + 1 < e else 0
        c2 = buf[p + 2] if p + 2 < e else 0
        c3 = buf[p + 3] if p + 3 < e else 0
        if c1 == _D0 and _D0 <= c2 <= _D3 and not (_D0 <= c3 <= _D9 or c3 == _DOT):
            g = c2 - _D0
            p += 3
        elif _D0 <= c1 <= _D3 and not (_D0 <= c2 <= _D9 or c2 == _DOT):
            g = c1 - _D0
            p += 2
        else:
            return LINE_NO_MATCH, -1
        while p < e and (buf[p] == _SP or buf[p] == _TAB):
            p += 1
    status = LINE_FAST
    motion = g >= 0
    # (?:L[ \t]*([-+]?(?:[0-9]{1,9}(?:\.[0-9]*)?|\.[0-9]+))[ \t]*)? for L in X Y Z A B C I J K R F
    for k in range(11):
        if p >= e:
            break
        if buf[p] != _WORD_CODES[k]:
            continue
        p += 1
        while p < e and (buf[p] == _SP or buf[p] == _TAB):
            p += 1
        neg = False
        if p < e and (buf[p] == _PLUS or buf[p] == _MINUS):
            neg = buf[p] == _MINUS
            p += 1
        mant = 0
        n_int = 0
        while p < e and _D0 <= buf[p] <= _D9:
            mant = mant * 10 + (buf[p] - _D0)
            n_int += 1
            p += 1
            if n_int > _MAX_INT_DIGITS:
                return LINE_NO_MATCH, -1
        frac = 0
        n_frac = 0
        exact = True
        if p < e and buf[p] == _DOT:
            p += 1
            pending = 0  # zeros after the point not yet multiplied in (trailing zeros do not change the value)
            while p < e and _D0 <= buf[p] <= _D9:
                d = buf[p] - _D0
                n_frac += 1
                p += 1
                if d == 0:
                    pending += 1
                elif exact:
                    for _ in range(pending + 1):
                        mant *= 10
                        if mant >= _TWO53:
                            exact = False
                            break
                    if exact:
                        mant += d
                        frac += pending + 1
                        if mant >= _TWO53 or frac > 22:
                            exact = False
                    pending = 0
            if n_int == 0 and n_frac == 0:
                return LINE_NO_MATCH, -1  # "." alone
        elif n_int == 0:
            return LINE_NO_MATCH, -1  # no number
        while p < e and (buf[p] == _SP or buf[p] == _TAB):
            p += 1
        if not exact:
            status = LINE_SLOW
        else:
            v = np.float64(mant) / _POW10[frac]
            vals[row, k] = -v if neg else v
        if k < 6:
            motion = True
    if p != e:
        return LINE_NO_MATCH, -1
    if not motion:
        return LINE_NO_MOTION, -1
    return status, g


@numba.njit(cache=True, nogil=True)
def scan_lines(buf, starts, lo, hi):
    """Scan lines lo..hi-1: status (int8: LINE_*), g (int8, -1 = no G word) and vals ((hi - lo, 11) float64, the
    values of X Y Z A B C I J K R F, NaN when absent; only meaningful where status == LINE_FAST)."""
    m = hi - lo
    status = np.empty(m, np.int8)
    gs = np.empty(m, np.int8)
    vals = np.empty((m, 11), np.float64)
    for r in range(m):
        st, g = _scan_line(buf, starts[lo + r], starts[lo + r + 1], vals, r)
        status[r] = st
        gs[r] = g
    return status, gs, vals


_OPEN, _SEMI = 40, 59
_LEADING_LETTERS = b"XYZIJKR"


@numba.njit(cache=True, nogil=True)
def _is_digit(c):
    return c >= _D0 and c <= _D9


@numba.njit(cache=True, nogil=True)
def _is_leading_letter(c):
    """One of X Y Z I J K R (upper case): the letters the writer's leading-zero style is judged on."""
    return c == 88 or c == 89 or c == 90 or c == 73 or c == 74 or c == 75 or c == 82


@numba.njit(cache=True, nogil=True)
def number_style(buf):
    """How the numbers of ``buf`` (uint8, a program's text; comments from ``(`` or ``;`` to the end of their line
    not read) are written, for ``Program.format_info``: (decimals (26,) int64: per letter A..Z the most digits after
    the point of its words ``letter [blanks] [sign] digits . digits``, -1 for none; bare: a word of X Y Z A B C F
    ends in a bare point; leading: 1 when the first number below 1 of a word X Y Z I J K R is written ``0.5``, 0 when
    ``.5``, -1 when there is none).

    Word for word what the regular expressions it replaces found (``_DECIMALS``'s letter, blanks, sign, point, as the
    byte-wise numpy pass read it; ``_LEADING_ZERO``'s first match): bytes, integers, no arithmetic on values."""
    n = buf.shape[0]
    decimals = np.full(26, -1, np.int64)
    bare = False
    leading = -1
    in_comment = False
    for d in range(n):
        c = buf[d]
        if c == _LF or c == _CR:
            in_comment = False
            continue
        if in_comment:
            continue
        if c == _OPEN or c == _SEMI:
            in_comment = True
            continue
        if c != _DOT:
            continue
        # digits after the point
        e = d + 1
        while e < n and _is_digit(buf[e]):
            e += 1
        frac = e - d - 1
        # before it: digits, an optional sign, blanks, the letter
        pos = d - 1
        while pos >= 0 and _is_digit(buf[pos]):
            pos -= 1
        if pos >= 0 and (buf[pos] == _PLUS or buf[pos] == _MINUS):
            pos -= 1
        while pos >= 0 and (buf[pos] == _SP or buf[pos] == _TAB):
            pos -= 1
        if pos >= 0:
            letter = buf[pos]
            if letter >= 97 and letter <= 122:
                letter -= 32
            if letter >= 65 and letter <= 90:
                k = letter - 65
                if frac > decimals[k]:
                    decimals[k] = frac
                if frac == 0 and (letter == 88 or letter == 89 or letter == 90 or letter == 65 or letter == 66
                                  or letter == 67 or letter == 70):
                    bare = True
        # the first ``[XYZIJKR][-+]?(0?)\.[0-9]``: its letter right before the point, or before a sign, a zero or both
        if leading < 0 and frac > 0:
            j = d - 1
            zero = j >= 0 and buf[j] == _D0
            if zero:
                j -= 1
            if j >= 0 and (buf[j] == _PLUS or buf[j] == _MINUS):
                j -= 1
            if j >= 0 and _is_leading_letter(buf[j]):
                leading = 1 if zero else 0
    return decimals, bare, leading


# The bytes a plain move may hold: N G X Y Z A B C F I J K R, digits, point, signs, blanks, line endings
_PLAIN_BYTES = np.zeros(256, np.bool_)
for _c in b"NGXYZABCFIJKR0123456789.+- \t\r\n":
    _PLAIN_BYTES[_c] = True


@numba.njit(cache=True, nogil=True)
def _digit_or_point(buf, i, end):
    return i < end and (_is_digit(buf[i]) or buf[i] == _DOT)


@numba.njit(cache=True, nogil=True)
def next_check_candidate(buf, plain, pos):
    """The first offset >= ``pos`` of ``buf`` (uint8, ASCII) where a block may need the checks word by word
    (``nc.check``), or -1: where one of its patterns matches -- a byte no plain move has (``plain``: True for the
    bytes one may), a G code other than G0..G3 (``G(?![ \t]*0?[0-3](?![0-9.]))``), a G followed by another on its
    line (``G[^G\n]*G``), an N not at the start of a line, an N with a sign (``N[ \t]*[-+]``).

    One pass over the bytes: a G0..G3 waits (``pending``) for another G on its line, found as the scan goes on,
    instead of a look ahead to the line's end at every G; the rest of the line is looked at only where another pattern
    matches after such a G (the G's offset is then the answer if a G follows on the line: it comes first)."""
    n = buf.shape[0]
    pending = -1  # a G0..G3 of this line before i, with no G after it so far
    for i in range(pos, n):
        c = buf[i]
        hit = False
        if not plain[c]:
            hit = True
        elif c == _G:
            if pending >= 0:
                return pending  # a G followed by another on its line
            j = i + 1
            while j < n and (buf[j] == _SP or buf[j] == _TAB):
                j += 1
            # G0..G3 (G00..G03): the lookahead's two ways, '0' then the digit, or the digit alone, either not
            # followed by a digit or a point
            more1 = j + 1 < n and ((buf[j + 1] >= _D0 and buf[j + 1] <= _D9) or buf[j + 1] == _DOT)
            more2 = j + 2 < n and ((buf[j + 2] >= _D0 and buf[j + 2] <= _D9) or buf[j + 2] == _DOT)
            if not ((j + 1 < n and buf[j] == _D0 and buf[j + 1] >= _D0 and buf[j + 1] <= _D3 and not more2)
                    or (j < n and buf[j] >= _D0 and buf[j] <= _D3 and not more1)):
                return i
            pending = i
        elif c == _N:
            if i > 0 and buf[i - 1] != _LF:
                hit = True
            else:
                j = i + 1
                while j < n and (buf[j] == _SP or buf[j] == _TAB):
                    j += 1
                hit = j < n and (buf[j] == _PLUS or buf[j] == _MINUS)
        elif c == _LF:
            pending = -1
        if hit:
            if pending >= 0:  # a G on the pending G's line after this byte: the G's match comes first
                k = i + 1
                while k < n and buf[k] != _G and buf[k] != _LF:
                    k += 1
                if k < n and buf[k] == _G:
                    return pending
            return i
    return -1


@numba.njit(cache=True, nogil=True)
def ijkr_after_linear(buf, a, b):
    """In ``buf[a:b]`` (uint8, ASCII): the offset of the first I J K or R word that follows a G0 / G1 (``G0?[01]``
    not followed by a digit or point) with no G between (line ends allowed), or -1 -- where
    ``G0?[01](?![0-9.])[^G\nIJKR]*+(?:\n[^G\nIJKR]*+)*+[IJKR]`` would end."""
    for g in range(a, b):
        if buf[g] != _G:
            continue
        j = g + 1
        end = -1
        if j + 1 < b and buf[j] == _D0 and (buf[j + 1] == _D0 or buf[j + 1] == 49) \
                and not _digit_or_point(buf, j + 2, b):
            end = j + 2
        elif j < b and (buf[j] == _D0 or buf[j] == 49) and not _digit_or_point(buf, j + 1, b):
            end = j + 1
        if end < 0:
            continue
        k = end
        while k < b and buf[k] != _G and buf[k] != 73 and buf[k] != 74 and buf[k] != 75 and buf[k] != 82:
            k += 1
        if k < b and buf[k] != _G:
            return k
    return -1


def scan_text(text: str):
    """(starts, buf) for an ASCII ``text``, or None when it is not ASCII."""
    if not text.isascii():
        return None
    buf = np.frombuffer(text.encode("ascii"), np.uint8)
    return line_starts(buf), buf
