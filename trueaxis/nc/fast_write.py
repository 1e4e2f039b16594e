"""The writer's compiled fast path: the bulk of the compensated motion blocks, rewritten straight into bytes.

What it does. Most compensated blocks of a program are *plain* (``post._PLAIN``: optional N, optional motion word
G0..G3, axis and centre words X Y Z A B C I J K in this order, optional R, optional F, blanks, nothing else) and are
written with absolute axis words, not split, not canned cycles. For those the writer's output is
``sep.join([N] + [G word] + axis words + [centre words] + [R] + [F]) + line ending`` (``post._rewrite_plain``: the
block's own centre words always go, its R word stays and new centre words are written only for a kept arc).
``scan`` checks that grammar for every candidate line of the program's text (bytes) and
finds the spans of its N and F words and the style of its G word (``G01`` when written with a leading zero, see
``post._motion_text``); lines it does not accept go through the Python path. ``assemble`` then writes the whole output
program in one pass: untouched lines copied, lines the Python path rewrote copied from their text, and the fast lines
built from their spans and the target values, each number formatted as ``gcode.write_number`` formats it.

Why hand-written (numba). The Python writer spends its time per line and per number: splitting the line ending,
matching the block, building and joining lists of words, and ``"%.5f" % x`` with its trailing-zero and sign rules for
every axis word -- about 14 us a five-axis block, which alone took a third of the whole post. Vectorising it with
numpy does not remove the per-line string work; a compiled loop over the bytes does. ``cache=True`` keeps the compile
(a few seconds) out of every run but the first.

Exactness of the numbers. ``write_number`` writes ``"%.{d}f" % x``: the exact binary value of ``x`` correctly rounded
to ``d`` decimals, ties to even. Here, for |x| 10**d < 2**53 and d <= 22 (else the line goes to the Python path):
s = 10**d is exact as a double (5**22 < 2**53); p = fl(|x| s) and the error-free product (Dekker's two-product with
Veltkamp's split -- numba has no fma -- exact since nothing overflows or underflows in this range) gives
|x| s = p + e exactly, |e| <= ulp(p)/2. With n = floor(p) and t = (p - n) - 0.5 (both exact), the exact fraction of
|x| s lies above, on or below one half as t + e does; when t != 0 it is a multiple of ulp(p) (p >= 1/4 here) and so
outweighs e: the sign of t decides; when t == 0 the sign of e decides, and e == 0 is an exact tie (then to even).
Below p < 1/4 the number rounds to 0. The rounded integer q (< 2**53 + 1) is then written in decimal with ``d``
digits after the point, trailing zeros dropped, no ``-0``, the program's leading-zero and trailing-point style.
"""

from __future__ import annotations

from ..compiled import numba  # numba, or the kernels compiled ahead of time (see ..compiled)
import numpy as np

MAX_DECIMALS = 22
_TWO53 = 9007199254740992.0
_P10 = np.array([float(10**i) for i in range(MAX_DECIMALS + 1)])  # exact: 10**i = 2**i 5**i, 5**22 < 2**53
_WORD_ORDER = np.frombuffer(b"XYZABCIJKRF", np.uint8).copy()  # the words after G, in their order
_WORD_MAX = 32  # bytes a written axis word can take: separator, letter, sign, 23 digits, point


@numba.njit(cache=True)
def _two_product_error(a, b, p):
    """e with a b = p + e exactly (p = fl(a b)); Dekker / Veltkamp, no fma."""
    c = 134217729.0 * a  # 2**27 + 1
    ah = c - (c - a)
    al = a - ah
    c = 134217729.0 * b
    bh = c - (c - b)
    bl = b - bh
    return ((ah * bh - p) + ah * bl + al * bh) + al * bl


@numba.njit(cache=True)
def _fits(x, d):
    """The compiled formatter writes ``x`` at ``d`` decimals exactly (finite, d <= 22, |x| 10**d < 2**53)."""
    if d < 0 or d > MAX_DECIMALS or not np.isfinite(x):
        return False
    return abs(x) * _P10[d] < _TWO53


@numba.njit(cache=True)
def _rounded(x, d):
    """round(|x| 10**d) of the exact binary |x|, ties to even, as an int64 (``_fits(x, d)`` assumed)."""
    ax = abs(x)
    s = _P10[d]
    p = ax * s
    if p < 0.25:
        return np.int64(0)
    n = np.floor(p)
    t = (p - n) - 0.5
    q = np.int64(n)
    if t > 0.0:
        return q + 1
    if t < 0.0:
        return q
    e = _two_product_error(ax, s, p)
    if e > 0.0:
        return q + 1
    if e < 0.0:
        return q
    return q + (q & 1)  # an exact tie: to even


@numba.njit(cache=True)
def _n_digits(q):
    n = 1
    while q >= 10:
        q //= 10
        n += 1
    return n


@numba.njit(cache=True)
def _put_number(buf, pos, x, d, leading_zero, trailing_point):
    """``write_number(x, d, leading_zero=.., trailing_point=..)`` at ``buf[pos:]``; returns the new position.
    ``_fits(x, d)`` assumed; ``buf`` has room for 26 more bytes. (The digits are written here, from the last one
    back, not by a helper: numba reference-counts an array at every call it is handed to, a cost per number.)"""
    q = _rounded(x, d)
    de = d
    if q == 0:
        de = 0
    else:
        while de > 0 and q % 10 == 0:  # trailing zeros of the fraction
            q //= 10
            de -= 1
    if q != 0 and x < 0.0:
        buf[pos] = 45  # "-"
        pos += 1
    # q's digits zero-padded on the left to de (``0.00q``), the point before the last de of them; no integer digit
    # when they are all the fraction's ("0" before the point with leading_zero), a trailing point when none is
    n_int = max(_n_digits(q), de) - de
    if n_int == 0 and leading_zero:
        buf[pos] = 48
        pos += 1
    end = pos + n_int + de + (1 if de > 0 or trailing_point else 0)
    i = end - 1
    if de == 0 and trailing_point:
        buf[i] = 46
        i -= 1
    # the fraction's digits, then the integer's: two loops written out, as a helper taking ``buf`` would be
    # reference-counted by numba at every call (NRT_incref/decref: the cost this layout removed)
    for _ in range(de):
        buf[i] = 48 + q % 10
        q //= 10
        i -= 1
    if de > 0:
        buf[i] = 46
        i -= 1
    for _ in range(n_int):
        buf[i] = 48 + q % 10
        q //= 10
        i -= 1
    return end


@numba.njit(cache=True)
def _upper(c):
    return c - 32 if 97 <= c <= 122 else c


@numba.njit(cache=True)
def _body_end(src, s, e):
    """End of a line's text without its line ending (``rstrip("\\r\\n")``)."""
    while e > s and (src[e - 1] == 10 or src[e - 1] == 13):
        e -= 1
    return e


@numba.njit(cache=True)
def _scan_line(src, s, e):
    """Match ``post._PLAIN`` on src[s:e]: (True, N start, N end, F start, F end, G style, R start, R end) (-1: none;
    G style 1: ``G01``-like, 0: other), or (False, -1, ...).

    The words after the G word are X Y Z A B C I J K R F, each at most once, in this order (R, kept as written when
    the block stays an arc, and F, kept as written, have their spans noted); each a letter, blanks, ``post._NUM``
    ([-+]? (digits [.] digits* | . digits)). The bytes are read here, not by helpers: numba reference-counts an
    array at every call it is handed to, a cost per word."""
    fail = (False, -1, -1, -1, -1, -1, -1, -1)
    n0, n1, f0, f1, g, r0, r1 = -1, -1, -1, -1, -1, -1, -1
    i = s
    while i < e and (src[i] == 32 or src[i] == 9):
        i += 1
    if i < e and _upper(src[i]) == 78:  # N digits
        j = i + 1
        while j < e and 48 <= src[j] <= 57:
            j += 1
        if j == i + 1:
            return fail
        n0, n1, i = i, j, j
        while i < e and (src[i] == 32 or src[i] == 9):
            i += 1
    if i < e and _upper(src[i]) == 71:  # G 0* [0-3], not followed by a digit or point
        j = i + 1
        while j < e and 48 <= src[j] <= 57:
            j += 1
        nd = j - i - 1
        if nd == 0 or (j < e and src[j] == 46) or not (48 <= src[j - 1] <= 51):
            return fail
        for t in range(i + 1, j - 1):
            if src[t] != 48:
                return fail
        g = 1 if nd == 2 else 0
        i = j
        while i < e and (src[i] == 32 or src[i] == 9):
            i += 1
    last = -1
    while i < e:
        c = _upper(src[i])
        a = -1
        for t in range(last + 1, 11):
            if _WORD_ORDER[t] == c:
                a = t
                break
        if a < 0:
            break
        j = i + 1
        while j < e and (src[j] == 32 or src[j] == 9):
            j += 1
        if j < e and (src[j] == 43 or src[j] == 45):
            j += 1
        d0 = j
        while j < e and 48 <= src[j] <= 57:
            j += 1
        if j > d0:
            if j < e and src[j] == 46:
                j += 1
                while j < e and 48 <= src[j] <= 57:
                    j += 1
        elif j < e and src[j] == 46:
            j += 1
            d0 = j
            while j < e and 48 <= src[j] <= 57:
                j += 1
            if j == d0:
                return fail
        else:
            return fail
        if a == 9:
            r0, r1 = i, j
        elif a == 10:
            f0, f1 = i, j
        last = a
        i = j
        while i < e and (src[i] == 32 or src[i] == 9):
            i += 1
    if i != e:
        return fail
    return (True, n0, n1, f0, f1, g, r0, r1)


@numba.njit(cache=True)
def scan(src, line_start, cand_line, cand_k, cand_motion, target, cols, dec, inch, n_extra, extra_val, extra_dec, ok,
         spans):
    """Which candidate lines the compiled writer takes, into ``ok`` (n,) bool and ``spans`` (n, 7) int64 (see
    ``_scan_line``; -1 where not ok); returns how many it takes. (Into the caller's arrays: shares of the candidates
    on the kernels' threads write their parts of the same arrays, which are not joined afterwards.)

    src: the program's bytes; line_start (L+1,): byte offset of every line; candidate c is line cand_line[c], its
    axis words the values target[cand_k[c], cols] at decimals dec[inch[cand_k[c]]] (per output axis), then
    n_extra[c] words more (a kept arc's centre) of values extra_val[c] at decimals extra_dec[c]; its motion word
    cand_motion[c] (0..3). A line is taken when it is plain and every number can be written exactly."""
    n = cand_line.size
    taken = 0
    for c in range(n):
        ok[c] = False
        for j in range(7):
            spans[c, j] = -1
        li = cand_line[c]
        s = line_start[li]
        e = _body_end(src, s, line_start[li + 1])
        m = cand_motion[c]
        if m < 0 or m > 9:
            continue
        plain, n0, n1, f0, f1, g, r0, r1 = _scan_line(src, s, e)
        if not plain:
            continue
        k = cand_k[c]
        good = True
        for a in range(cols.size):
            if not _fits(target[k, cols[a]], dec[1 if inch[k] else 0, a]):
                good = False
                break
        for a in range(n_extra[c]):
            if not _fits(extra_val[c, a], extra_dec[c, a]):
                good = False
        if good:
            ok[c] = True
            spans[c, 0], spans[c, 1], spans[c, 2], spans[c, 3] = n0, n1, f0, f1
            spans[c, 4], spans[c, 5], spans[c, 6] = g, r0, r1
            taken += 1
    return taken


@numba.njit(cache=True)
def _grown(buf, pos, need):
    """A buffer of at least ``pos + need`` bytes, its first ``pos`` those of ``buf`` (called where ``buf`` is short)."""
    out = np.empty(max(2 * buf.size, pos + need), np.uint8)
    out[:pos] = buf[:pos]
    return out


@numba.njit(cache=True)
def _copy(buf, pos, src, s, e):
    for i in range(e - s):
        buf[pos + i] = src[s + i]
    return pos + e - s


@numba.njit(cache=True)
def assemble(src, line_start, mode, cand_of_line, cand_k, cand_motion, spans, target, cols, letters, dec, inch,
             n_extra, extra_val, extra_letter, extra_dec, keep_r, leading_zero, trailing_point, sep, blob, blob_start,
             blob_end):
    """The output program's bytes. Per line li: mode 0, src's line as it is; 1, candidate cand_of_line[li] rewritten
    (``scan`` accepted it): [N sep] G word, sep letter number per output axis, the extra words (a kept arc's
    centre), [sep R] (when keep_r), [sep F], the line ending; 2, the text blob[blob_start[li]:blob_end[li]] (the
    Python path's). ``sep``: separator byte, or -1 for none.

    The rewritten lines' bytes are copied here, not by helpers (numba reference-counts an array at every call it is
    handed to, a cost per word); a number is one call (``_put_number``)."""
    n_lines = mode.size
    n_out = cols.size
    buf = np.empty(src.size + blob.size + 16 * n_lines + 64, np.uint8)
    pos = 0
    for li in range(n_lines):
        s = line_start[li]
        e = line_start[li + 1]
        md = mode[li]
        if md == 0:
            if pos + (e - s) > buf.size:
                buf = _grown(buf, pos, e - s)
            for t in range(s, e):
                buf[pos] = src[t]
                pos += 1
            continue
        if md == 2:
            if pos + (blob_end[li] - blob_start[li]) > buf.size:
                buf = _grown(buf, pos, blob_end[li] - blob_start[li])
            for t in range(blob_start[li], blob_end[li]):
                buf[pos] = blob[t]
                pos += 1
            continue
        c = cand_of_line[li]
        k = cand_k[c]
        need = (e - s) + _WORD_MAX * (n_out + n_extra[c] + 1)
        if pos + need > buf.size:
            buf = _grown(buf, pos, need)
        if spans[c, 0] >= 0:
            for t in range(spans[c, 0], spans[c, 1]):
                buf[pos] = src[t]
                pos += 1
            if sep >= 0:
                buf[pos] = sep
                pos += 1
        buf[pos] = 71  # "G"
        pos += 1
        if spans[c, 4] == 1:
            buf[pos] = 48
            pos += 1
        buf[pos] = 48 + cand_motion[c]
        pos += 1
        row = 1 if inch[k] else 0
        for a in range(n_out):
            if sep >= 0:
                buf[pos] = sep
                pos += 1
            buf[pos] = letters[a]
            pos = _put_number(buf, pos + 1, target[k, cols[a]], dec[row, a], leading_zero, trailing_point)
        for a in range(n_extra[c]):
            if sep >= 0:
                buf[pos] = sep
                pos += 1
            buf[pos] = extra_letter[c, a]
            pos = _put_number(buf, pos + 1, extra_val[c, a], extra_dec[c, a], leading_zero, trailing_point)
        if keep_r[c] and spans[c, 5] >= 0:
            if sep >= 0:
                buf[pos] = sep
                pos += 1
            for t in range(spans[c, 5], spans[c, 6]):
                buf[pos] = src[t]
                pos += 1
        if spans[c, 2] >= 0:
            if sep >= 0:
                buf[pos] = sep
                pos += 1
            for t in range(spans[c, 2], spans[c, 3]):
                buf[pos] = src[t]
                pos += 1
        be = e
        while be > s and (src[be - 1] == 10 or src[be - 1] == 13):
            be -= 1
        for t in range(be, e):
            buf[pos] = src[t]
            pos += 1
    return buf[:pos]


@numba.njit(cache=True)
def _put_words(buf, pos, pts, i, cols, letters, dec_row, leading_zero, trailing_point, sep):
    """The axis words of point ``pts[i]`` (sep letter number per output axis) at ``buf[pos:]``."""
    for a in range(cols.size):
        if sep >= 0:
            buf[pos] = sep
            pos += 1
        buf[pos] = letters[a]
        pos = _put_number(buf, pos + 1, pts[i, cols[a]], dec_row[a], leading_zero, trailing_point)
    return pos


@numba.njit(cache=True)
def _put_row_words(buf, pos, i, count, values, letters, decimals, leading_zero, trailing_point, sep):
    """The first ``count[i]`` words of row ``i`` of a word table (letter, value, decimals) at ``buf[pos:]``: a kept
    line's extra words, or a piece's centre words (none, or two: a fitted sub-arc's)."""
    for a in range(count[i]):
        if sep >= 0:
            buf[pos] = sep
            pos += 1
        buf[pos] = letters[i, a]
        pos = _put_number(buf, pos + 1, values[i, a], decimals[i, a], leading_zero, trailing_point)
    return pos


@numba.njit(cache=True)
def _pieces_fit(pts, lo, hi, cols, dec_row, n_centre, centre_val, centre_dec):
    """Every number of the pieces lo..hi-1 can be written exactly."""
    for i in range(lo, hi):
        for a in range(cols.size):
            if not _fits(pts[i, cols[a]], dec_row[a]):
                return False
        for a in range(n_centre[i]):
            if not _fits(centre_val[i, a], centre_dec[i, a]):
                return False
    return True


@numba.njit(cache=True)
def pieces(src, line_start, cand_line, first_motion, piece_code, piece_first, pts, cols, letters, dec, inch,
           n_centre, centre_val, centre_letter, centre_dec, leading_zero, trailing_point, sep):
    """The lines of split moves and fitted arcs (``post._Poster._split_block`` in absolute words, without G93), as
    bytes: (ok (m,) bool, blob, blob_start (m,), blob_end (m,)): candidate c's text is blob[blob_start[c]:
    blob_end[c]] when ok[c] (a plain line, see ``_scan_line``, whose numbers are all written exactly), else the
    Python path writes it.

    Candidate c is line cand_line[c]; its pieces are pts[piece_first[c]:piece_first[c + 1]] (the block's own end
    last), at decimals dec[inch[c]] per output axis (cols, letters). The line itself goes to the first piece's end:
    [N sep] G word (motion first_motion[c], in the line's style), the axis words, the piece's centre words, [sep F],
    the line ending; each further piece i is ``G`` piece_code[i], its axis words and centre words, the line ending.
    A piece's centre words (a fitted sub-arc's): n_centre[i] (0 or 2) letters centre_letter[i], values centre_val[i]
    at decimals centre_dec[i]. ``sep``: separator byte, or -1 for none."""
    m = cand_line.size
    ok = np.zeros(m, np.bool_)
    blob_start = np.zeros(m, np.int64)
    blob_end = np.zeros(m, np.int64)
    buf = np.empty(64 * (pts.shape[0] + m) + 64, np.uint8)
    pos = 0
    for c in range(m):
        li = cand_line[c]
        s = line_start[li]
        e = line_start[li + 1]
        be = _body_end(src, s, e)
        lo = piece_first[c]
        hi = piece_first[c + 1]
        row = 1 if inch[c] else 0
        if hi <= lo:
            continue
        plain, n0, n1, f0, f1, g, _, _ = _scan_line(src, s, be)
        if not plain:
            continue
        if not _pieces_fit(pts, lo, hi, cols, dec[row], n_centre, centre_val, centre_dec):
            continue
        ok[c] = True
        blob_start[c] = pos
        need = (e - s) + (hi - lo) * (_WORD_MAX * (cols.size + 3) + (e - be))
        if pos + need > buf.size:
            buf = _grown(buf, pos, need)
        if n0 >= 0:
            pos = _copy(buf, pos, src, n0, n1)
            if sep >= 0:
                buf[pos] = sep
                pos += 1
        buf[pos] = 71  # "G"
        pos += 1
        if g == 1:
            buf[pos] = 48
            pos += 1
        buf[pos] = 48 + first_motion[c]
        pos += 1
        pos = _put_words(buf, pos, pts, lo, cols, letters, dec[row], leading_zero, trailing_point, sep)
        pos = _put_row_words(buf, pos, lo, n_centre, centre_val, centre_letter, centre_dec, leading_zero,
                          trailing_point, sep)
        if f0 >= 0:
            if sep >= 0:
                buf[pos] = sep
                pos += 1
            pos = _copy(buf, pos, src, f0, f1)
        pos = _copy(buf, pos, src, be, e)
        for i in range(lo + 1, hi):
            buf[pos] = 71
            buf[pos + 1] = 48 + piece_code[i]
            pos = _put_words(buf, pos + 2, pts, i, cols, letters, dec[row], leading_zero, trailing_point, sep)
            pos = _put_row_words(buf, pos, i, n_centre, centre_val, centre_letter, centre_dec, leading_zero,
                              trailing_point, sep)
            pos = _copy(buf, pos, src, be, e)
        blob_end[c] = pos
    return ok, buf[:pos], blob_start, blob_end


# ------------------------------------------------------------------------------------ Python entry points -----


def separator_code(sep: str) -> int | None:
    """The separator as ``assemble`` takes it (-1 for none, else its byte), or None when the fast path cannot write
    it (anything but no separator or one ASCII character)."""
    if sep == "":
        return -1
    if len(sep) == 1 and sep.isascii():
        return ord(sep)
    return None


def format_number(value: float, decimals: int, *, leading_zero: bool = True, trailing_point: bool = False):
    """``gcode.write_number`` by the compiled formatter, or None where it does not write the number (non-finite,
    decimals > 22, |value| 10**decimals >= 2**53)."""
    if not _fits(float(value), int(decimals)):
        return None
    buf = np.empty(64, np.uint8)
    n = _put_number(buf, 0, float(value), int(decimals), bool(leading_zero), bool(trailing_point))
    return buf[:n].tobytes().decode("ascii")


def rewrite_line(line: str, motion: int, values, letters: str, decimals, *, leading_zero: bool = True,
                 trailing_point: bool = False, sep: str = " ", arc: bool = False, centre=()):
    """One line rewritten by the compiled writer, as the post's Python path rewrites a plain block (``rewrite_block``
    with the words ``letter + write_number(value, decimals)``, then for a kept arc (``arc``) its centre words
    ``centre``: (letter, value, decimals) each, at most two), line ending kept; None when the compiled writer does not
    take the line (not plain, not ASCII, a number it does not write)."""
    code = separator_code(sep)
    if code is None or not line.isascii():
        return None
    src = np.frombuffer(line.encode("ascii"), np.uint8)
    n_out = len(letters)
    target = np.asarray(values, float).reshape(1, n_out)
    cols = np.arange(n_out, dtype=np.int64)
    dec = np.asarray(decimals, np.int64).reshape(1, n_out).repeat(2, axis=0)
    line_start = np.array([0, src.size], np.int64)
    one = np.zeros(1, np.int64)
    motion_a = np.array([motion], np.int64)
    inch = np.zeros(1, np.bool_)
    n_extra = np.array([len(centre)], np.int64)
    extra_val = np.zeros((1, 2))
    extra_letter = np.zeros((1, 2), np.uint8)
    extra_dec = np.zeros((1, 2), np.int64)
    for j, (c, v, d) in enumerate(centre):
        extra_letter[0, j], extra_val[0, j], extra_dec[0, j] = ord(c), v, d
    ok, spans = np.zeros(1, np.bool_), np.empty((1, 7), np.int64)
    scan(src, line_start, one, one, motion_a, target, cols, dec, inch, n_extra, extra_val, extra_dec, ok, spans)
    if not ok[0]:
        return None
    out = assemble(src, line_start, np.ones(1, np.int8), one, one, motion_a, spans, target, cols,
                   np.frombuffer(letters.encode("ascii"), np.uint8), dec, inch, n_extra, extra_val, extra_letter,
                   extra_dec, np.array([bool(arc)]), bool(leading_zero), bool(trailing_point), code,
                   np.frombuffer(b"", np.uint8), one, one)
    return out.tobytes().decode("ascii")
