"""ECD ``events.txt`` ("t x y p" per line): a fast streaming reader and a vectorized writer.

Reading speed matters (a 60 s ECD file has 20-200 M events), so the file is read in byte blocks that end
at a newline and each block is parsed with whole-array numpy operations (two worker threads, numpy releases
the GIL). Three tiers, from fast to exact:

1. ``_parse_fast``: lines of exactly ``t x y p`` separated by single spaces (LF or CRLF line ends); t made of digits and one '.',
   x/y unsigned integers, p in {0, 1, -1}. Covers ECD files and our writer's output.
2. Blocks with comments, blank lines, tabs or repeated spaces are normalized line by line in Python and
   parsed again by tier 1.
3. Anything else (exponents, '+1', sub-pixel coordinates, garbage) is parsed per line with ``float``; a bad
   line raises ``InputError`` naming the file and line number.
"""
from __future__ import annotations

import os
from collections import deque
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path
from typing import Iterator

import numpy as np

from ..errors import InputError
from ..events import Events, polarity_word
from ._common import Block

BLOCK_BYTES = 8 << 20  # ~350 k events per block
_XY_MAX = 65535  # pixel coordinates are stored as uint16: a larger one is refused, never wrapped
_EXPECTED = "expected 't x y p' (time in seconds, pixel x, pixel y, polarity 0/1 or -1/+1)"


# ------------------------------------------------------------------------------------------------
# tier 1: vectorized parser
_U = np.uint64


def _swar8(w: np.ndarray):
    """Eight ASCII digits packed in a little-endian uint64 (first character lowest) -> (value, all digits?)."""
    hi = _U(0xF0F0F0F0F0F0F0F0)
    ok = ((w & hi) == _U(0x3030303030303030)) & (((w + _U(0x0606060606060606)) & hi) == _U(0x3030303030303030))
    v = w & _U(0x0F0F0F0F0F0F0F0F)
    v = v * _U(10) + (v >> _U(8))
    v = ((v & _U(0x000000FF000000FF)) * _U(100 + (1000000 << 32))
         + ((v >> _U(16)) & _U(0x000000FF000000FF)) * _U(1 + (10000 << 32))) >> _U(32)
    return v, bool(ok.all())


def _t_nine_decimals(a: np.ndarray, words: np.ndarray, ls: np.ndarray, end: np.ndarray):
    """Timestamps 'S.FFFFFFFFF' (ECD and our writer): the 9 decimals parsed 8 at a time (SWAR); else None."""
    if (end - 10 < ls).any() or not (a[end - 10] == 46).all():
        return None
    frac, ok = _swar8(words[end - 9])
    d9 = a[end - 1] - np.uint8(48)
    if not ok or (d9 > 9).any():
        return None
    ilen = end - 10 - ls
    if int(ilen.max()) > 12:
        return None
    ip = np.zeros(len(end), np.int64)
    mul = 1
    for k in range(1, int(ilen.max()) + 1):
        inside = ilen >= k
        d = a[end - 10 - k] - np.uint8(48)
        if ((d > 9) & inside).any():
            return None
        ip += np.where(inside, d, 0).astype(np.int64) * mul
        mul *= 10
    frac = frac.astype(np.int64) * 10 + d9
    if int(ilen.max()) <= 9:  # exact integer mantissa: one rounding (exact decimal -> double below 2**53)
        return (ip * 1_000_000_000 + frac) / 1e9
    return ip.astype(np.float64) + frac / 1e9  # e.g. Unix time in seconds: within one ulp


_PAD = 8
_LOW_ZEROS = np.array([int("30" * m, 16) if m else 0 for m in range(9)], dtype=np.uint64)


def _uint_swar(words: np.ndarray, end: np.ndarray, length: np.ndarray):
    """Unsigned integers of 1..8 digits ending (exclusive) at ``end``: one 8-byte load each, leading
    bytes replaced by '0'. Returns (values, all digits?)."""
    shift = ((8 - length) * 8).astype(np.uint64)
    w = ((words[end - 8] >> shift) << shift) | _LOW_ZEROS[8 - length]
    return _swar8(w)


def _parse_fast(buf: bytes):
    """Parse a block of complete lines; return (t, x, y, p) or None if the block needs a slower tier."""
    if not buf.endswith(b"\n"):
        return None
    a = np.frombuffer(b"0" * _PAD + buf, np.uint8)  # padding: 8-byte loads never start before the data
    nl = np.flatnonzero(a == 10)
    n = len(nl)
    if n == 0:
        return None
    sp = np.flatnonzero(a == 32)
    if len(sp) != 3 * n:
        return None
    sp = sp.reshape(n, 3)
    ls = np.empty(n, np.int64)
    ls[0] = _PAD
    ls[1:] = nl[:-1] + 1
    le = nl - (a[nl - 1] == 13)  # line end, without a '\r' of Windows line endings
    if not ((sp[:, 0] > ls).all() and (sp[:, 2] < le - 1).all()):
        return None
    xlen, ylen = sp[:, 1] - sp[:, 0] - 1, sp[:, 2] - sp[:, 1] - 1
    if xlen.max() > 5 or ylen.max() > 5 or xlen.min() < 1 or ylen.min() < 1:
        return None
    words = np.ndarray(shape=(len(a) - 7,), dtype="<u8", buffer=a, strides=(1,))  # unaligned 8-byte view
    x, ok = _uint_swar(words, sp[:, 1], xlen)
    if not ok:
        return None
    y, ok = _uint_swar(words, sp[:, 2], ylen)
    if not ok or int(x.max()) > _XY_MAX or int(y.max()) > _XY_MAX:  # 5 digits reach 99999: the exact tier names it
        return None
    plen = le - sp[:, 2] - 1
    last = a[le - 1]
    okp = ((plen == 1) & ((last == 48) | (last == 49))) | ((plen == 2) & (last == 49) & (a[le - 2] == 45))
    if not okp.all():
        return None
    p = np.where((last == 49) & (plen == 1), 1, -1).astype(np.int8)
    # t: digits with at most one '.'; value = mantissa / 10**(digits after the dot) (correctly rounded
    # while the mantissa is below 2**53, e.g. 9 decimals and t < 9e6 s)
    end = sp[:, 0]
    t = _t_nine_decimals(a, words, ls, end)
    if t is not None:
        return t, x.astype(np.uint16), y.astype(np.uint16), p
    tlen = end - ls
    if int(tlen.max()) > 19:
        return None
    mant = np.zeros(n, np.int64)
    mul = np.ones(n, np.int64)
    frac = np.zeros(n, np.int64)
    ndot = np.zeros(n, np.int8)
    for k in range(1, int(tlen.max()) + 1):
        c = a[end - k]
        inside = tlen >= k
        d = c - np.uint8(48)
        isd = (d <= 9) & inside
        isdot = (c == 46) & inside
        if ((~isd) & (~isdot) & inside).any():
            return None
        if isdot.any():
            frac = np.where(isdot, k - 1, frac)
            ndot += isdot
        mant += np.where(isd, d, 0) * mul
        mul = np.where(isd, mul * 10, mul)
    if (ndot > 1).any() or (mul == 1).any():
        return None
    t = mant / (10.0 ** frac)
    return t, x.astype(np.uint16), y.astype(np.uint16), p


# ------------------------------------------------------------------------------------------------
# tiers 2 and 3
def _normalize(buf: bytes, first_line: int):
    """Drop comments and blank lines, single-space the tokens; return (bytes, line numbers, token lists)."""
    out, lines, toks = [], [], []
    for i, raw in enumerate(buf.split(b"\n")):
        k = raw.find(b"#")
        if k >= 0:
            raw = raw[:k]
        parts = raw.split()
        if not parts:
            continue
        out.append(b" ".join(parts))
        lines.append(first_line + i)
        toks.append(parts)
    return b"\n".join(out) + b"\n" if out else b"", np.asarray(lines, np.int64), toks


class _LineError(Exception):
    """A bad line found in a worker thread; the line number is relative to the block."""

    def __init__(self, message: str, line: int):
        super().__init__(message)
        self.message, self.line = message, line


def _parse_exact(toks: list, lines: np.ndarray):
    """Per-line parse with exact error positions."""
    n = len(toks)
    t = np.empty(n)
    xy = np.empty((n, 2))
    p = np.empty(n, np.int8)
    for i, parts in enumerate(toks):
        line = int(lines[i])
        text = b" ".join(parts).decode("utf-8", "replace")
        if len(parts) != 4:
            raise _LineError(f"{_EXPECTED}, got {len(parts)} values: {text[:80]!r}", line)
        try:
            t[i] = float(parts[0])
            xy[i, 0] = float(parts[1])
            xy[i, 1] = float(parts[2])
        except ValueError:
            raise _LineError(f"{_EXPECTED}, got {text[:80]!r}", line) from None
        sign = polarity_word(parts[3].decode("utf-8", "replace"))
        if sign is None:
            raise _LineError(f"polarity must be 0/1 or -1/+1 (or +/-), got {parts[3].decode(errors='replace')!r}", line)
        p[i] = sign
        if not (np.isfinite(xy[i]).all() and (xy[i] >= 0).all()):
            raise _LineError(f"pixel coordinates must be finite and >= 0, got {text[:80]!r}", line)
        if xy[i].max() > _XY_MAX:
            k = int(np.argmax(xy[i]))
            raise _LineError(f"{'xy'[k]}={parts[1 + k].decode(errors='replace')} is beyond any sensor "
                             f"(pixel coordinates are at most {_XY_MAX})", line)
    if n and np.all(xy == np.round(xy)):
        return Events(t, xy[:, 0].astype(np.uint16), xy[:, 1].astype(np.uint16), p)
    return Events(t, xy[:, 0].astype(np.float32), xy[:, 1].astype(np.float32), p)


def parse_block(buf: bytes) -> Block:
    """Parse complete lines through the three tiers. Line numbers are relative to the block (first = 1)
    and ``first_index`` is 0: ``_place`` shifts them once the preceding blocks are known."""
    r = _parse_fast(buf)
    if r is not None:
        return Block(Events(*r), None, 0, line0=1, nlines=len(r[0]))
    norm, lines, toks = _normalize(buf, 1)
    nlines = buf.count(b"\n")
    if not norm:
        return Block(Events.empty(), np.zeros(0, np.int64), 0, nlines=nlines)
    r = _parse_fast(norm)
    if r is not None:
        return Block(Events(*r), lines, 0, nlines=nlines)
    try:
        return Block(_parse_exact(toks, lines), lines, 0, nlines=nlines)
    except _LineError as exc:
        exc.nlines = nlines
        return exc


def _place(result, line_base: int, index: int, source: str) -> Block:
    """Shift a block's relative positions by the lines and events before it; raise its parse error."""
    if isinstance(result, _LineError):
        raise InputError(result.message, source=source, line=line_base + result.line)
    result.first_index = index
    if result.lines is not None:
        result.lines = result.lines + line_base
    else:
        result.line0 += line_base
    return result


def _byte_blocks(path: Path, block_bytes: int, offset: int = 0) -> Iterator[bytes]:
    """Yield byte blocks of complete lines from byte ``offset`` on (a last line without newline gets one)."""
    with open(path, "rb") as f:
        f.seek(offset)
        rest = b""
        while True:
            chunk = f.read(block_bytes)
            if not chunk:
                if rest:
                    yield rest + b"\n"
                return
            k = chunk.rfind(b"\n") + 1
            if k == 0:
                rest += chunk
                continue
            yield rest + memoryview(chunk)[:k] if rest else (chunk if k == len(chunk) else chunk[:k])
            rest = chunk[k:]


def iter_txt_blocks(path, block_bytes: int | None = None, threads: int = 2, offset: int = 0,
                    first_line: int = 1) -> Iterator[Block]:
    """Parsed blocks of an events.txt file, parsed by a small thread pool with bounded read-ahead.

    Workers parse blocks independently (relative line numbers); the consumer places them in order.
    ``offset``/``first_line``: start at that byte, which is the start of that 1-based line.
    """
    block_bytes = block_bytes or BLOCK_BYTES
    path = Path(path)
    source = str(path)
    line_base, index = first_line - 1, 0
    if threads <= 1:
        for buf in _byte_blocks(path, block_bytes, offset):
            b = _place(parse_block(buf), line_base, index, source)
            line_base += b.nlines
            index += len(b.events)
            yield b
        return
    with ThreadPoolExecutor(threads) as ex:
        pending: deque = deque()
        blocks = _byte_blocks(path, block_bytes, offset)
        while True:
            while len(pending) <= threads:
                buf = next(blocks, None)
                if buf is None:
                    break
                pending.append(ex.submit(parse_block, buf))
            if not pending:
                return
            b = _place(pending.popleft().result(), line_base, index, source)
            line_base += b.nlines
            index += len(b.events)
            yield b


# ------------------------------------------------------------------------------------------------
# cheap metadata
def _data_line(raw: bytes) -> bytes | None:
    k = raw.find(b"#")
    if k >= 0:
        raw = raw[:k]
    raw = raw.strip()
    return raw or None


def _t_of(raw: bytes, source: str, where: str) -> float:
    parts = raw.split()
    try:
        if len(parts) != 4:
            raise ValueError
        return float(parts[0])
    except ValueError:
        raise InputError(f"{where}: {_EXPECTED}, got {raw[:80].decode(errors='replace')!r}", source=source) from None


def txt_time_range(path) -> tuple[float, float]:
    """(first t, last t) from the first data line and the file's tail, without reading the whole file."""
    path = Path(path)
    source = str(path)
    first = None
    with open(path, "rb") as f:
        for lineno, raw in enumerate(f, 1):
            d = _data_line(raw)
            if d is not None:
                first = _t_of(d, source, f"line {lineno}")
                break
        if first is None:
            raise InputError("the file holds no events", source=source)
        size = os.fstat(f.fileno()).st_size
        tail = 1 << 16
        while True:
            start = max(0, size - tail)
            f.seek(start)
            data = f.read()
            lines = data.split(b"\n")
            if start > 0:
                lines = lines[1:]  # may be a partial line
            for raw in reversed(lines):
                d = _data_line(raw)
                if d is not None:
                    return first, _t_of(d, source, "last line")
            if start == 0:
                raise InputError("the file holds no events", source=source)
            tail *= 4


def txt_seek(path, t_start: float, min_skip: int = 32 << 20) -> tuple[int, int]:
    """(byte offset, 1-based line number) of a line start before the first event with t >= t_start.

    Bisects on byte offsets (timestamps are sorted), reading one line per step, so reading a late
    part of a long file does not parse everything before it. Files smaller than ``min_skip`` bytes
    (or a time before the second half) give (0, 1).
    """
    path = Path(path)
    size = path.stat().st_size
    lo, hi = 0, size
    with open(path, "rb") as f:
        while hi - lo > min_skip:
            mid = (lo + hi) // 2
            f.seek(mid)
            f.readline()  # skip to the next line start
            start = f.tell()
            t = None
            while t is None:
                raw = f.readline()
                if not raw:
                    break
                d = _data_line(raw)
                if d is not None:
                    t = _t_of(d, str(path), f"byte {start}")
            if t is None or t >= t_start:
                hi = mid
            else:
                lo = start
        if lo == 0:
            return 0, 1
        f.seek(0)
        nl, todo = 0, lo
        while todo:
            chunk = f.read(min(todo, 16 << 20))
            nl += chunk.count(b"\n")
            todo -= len(chunk)
    return lo, nl + 1


def txt_count_lines(path) -> int:
    """Number of data lines, counted on raw bytes (comment lines and empty lines excluded)."""
    n = 0
    comment = 0
    last = b"\n"
    with open(path, "rb") as f:
        prev_end = b"\n"
        while True:
            chunk = f.read(16 << 20)
            if not chunk:
                break
            n += chunk.count(b"\n")
            joined = prev_end + chunk
            comment += joined.count(b"\n#") + joined.count(b"\n\n")
            prev_end = chunk[-1:]
            last = chunk[-1:]
    if last != b"\n":
        n += 1
    return max(n - comment, 0)


# ------------------------------------------------------------------------------------------------
# writer
def _digits(v: np.ndarray, ndig: int) -> np.ndarray:
    """(N, ndig) ASCII digits of non-negative integers, zero-padded on the left."""
    dt = np.uint32 if len(v) and int(v.max()) < 2**32 else np.int64  # 32-bit division is much faster
    pows = (10 ** np.arange(ndig - 1, -1, -1, dtype=np.int64)).astype(dt)
    return ((v.astype(dt)[:, None] // pows) % dt(10) + dt(48)).astype(np.uint8)


def _ndigits(v: np.ndarray) -> np.ndarray:
    n = np.ones(len(v), np.int64)
    m = v.copy()
    while True:
        m //= 10
        more = m > 0
        if not more.any():
            return n
        n += more


def format_events_txt(events: Events) -> bytes:
    """ECD text lines "t x y p" (t with 9 decimals, p in {0,1}), built without a per-line Python loop."""
    n = len(events)
    if n == 0:
        return b""
    t = events.t
    if events.has_subpixel_coordinates or not np.isfinite(t).all() or (t < 0).any() or t.max() >= 1e9:
        pv = (events.p > 0).astype(int)
        return "".join(f"{ti:.9f} {xi:g} {yi:g} {pi}\n" for ti, xi, yi, pi in
                       zip(t.tolist(), events.x.tolist(), events.y.tolist(), pv.tolist())).encode()
    ns = np.round(t * 1e9).astype(np.int64)
    sec, frac = np.divmod(ns, 1_000_000_000)
    x = events.x.astype(np.int64)
    y = events.y.astype(np.int64)
    cols, masks = [], []

    def number(v):
        nd = _ndigits(v)
        w = int(nd.max())
        cols.append(_digits(v, w))
        masks.append(np.arange(w)[None, :] >= (w - nd)[:, None])

    def const(ch: bytes, width: int = 1):
        cols.append(np.broadcast_to(np.frombuffer(ch, np.uint8), (n, width)))
        masks.append(np.ones((n, width), bool))

    number(sec)
    const(b".")
    cols.append(_digits(frac, 9))
    masks.append(np.ones((n, 9), bool))
    const(b" ")
    number(x)
    const(b" ")
    number(y)
    const(b" ")
    cols.append(np.where(events.p > 0, 49, 48).astype(np.uint8)[:, None])
    masks.append(np.ones((n, 1), bool))
    const(b"\n")
    chars = np.concatenate(cols, axis=1)
    mask = np.concatenate(masks, axis=1)
    return chars[mask].tobytes()


class EventsTxtWriter:
    """Stream events into an ECD events.txt: ``with EventsTxtWriter(p) as w: w.append(ev)``."""

    def __init__(self, path, chunk: int = 1_000_000):
        self.path = Path(path)
        self._chunk = chunk
        self._f = None
        self.count = 0

    def __enter__(self):
        self._f = open(self.path, "wb")
        return self

    def append(self, events: Events):
        if self._f is None:
            raise RuntimeError("EventsTxtWriter must be used as a context manager")
        for i in range(0, len(events), self._chunk):
            self._f.write(format_events_txt(events[i:i + self._chunk]))
        self.count += len(events)

    def close(self):
        if self._f is not None:
            self._f.close()
            self._f = None

    def __exit__(self, *exc):
        self.close()
        return False


def write_events_txt(path, events: Events) -> Path:
    """Write all events to an ECD events.txt ("t x y p", p in {0,1}, t with 9 decimals)."""
    with EventsTxtWriter(path) as w:
        w.append(events)
    return Path(path)
