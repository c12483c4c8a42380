"""
Compiled reading and writing of a batch's points (numba, cache=True) for nodes.codec.

A stream's batches repeat one shape (names, number of points, values per point), so every field of
every point sits at a byte offset known from the first batch (codec._BatchShape, the encoder's
templates). These kernels read or write all points of such a batch in one call: about a quarter of
the numpy views they replace (each numpy call costs about a microsecond here, and a batch took a
dozen). Little-endian CDR on a little-endian host only; the codec keeps its numpy paths for the
rest.

`meta` (int64) describes the points of one shape: M_* below, then the field offsets of point 0
(from M_HEAD, when it has a layout of its own: it starts at the other 8-byte phase) and of the
strided run of the others (from M_RUN_LAYOUT), each in the order of LAYOUT_FIELDS, relative to the
point's first byte.
"""
import numpy as np
from numba import njit

LAYOUT_FIELDS = ('n_pos', 'n_vel', 'n_acc', 'n_eff', 'pos', 'eff', 'sec', 'nsec')
M_START, M_RUN, M_COUNT, M_HAS_HEAD, M_N_POS, M_N_EFF, M_SIZE = range(7)
M_HEAD = 7
M_RUN_LAYOUT = M_HEAD + len(LAYOUT_FIELDS)
M_LENGTH = M_RUN_LAYOUT + len(LAYOUT_FIELDS)
(F_N_POS, F_N_VEL, F_N_ACC, F_N_EFF, F_POS, F_EFF, F_SEC, F_NSEC) = range(len(LAYOUT_FIELDS))


def make_meta(start: int, run: int, count: int, n_pos: int, n_eff: int, size: int,
              head, layout) -> np.ndarray:
    """
    Return the meta vector of a shape.

    start: byte of point 0; run: byte of the strided points (start, or after point 0 when `head`,
    its own layout, is given); size: bytes per strided point; head, layout: objects with the
    LAYOUT_FIELDS attributes (codec._PointLayout). None when the fields are not aligned as CDR
    aligns them (the kernels read them as words and doubles).
    """
    for at, lay in ((start, head), (run, layout)):
        if lay is None:
            continue
        if any((at + getattr(lay, f)) % 4 for f in LAYOUT_FIELDS[:4] + LAYOUT_FIELDS[6:]) or \
                any((at + getattr(lay, f)) % 8 != 4 for f, n in (('pos', n_pos), ('eff', n_eff))
                    if n):
            return None     # not aligned as CDR aligns (never for codec's shapes): numpy path
    if (run - start - (head.size if head is not None else 0)) or size % 8:
        return None
    meta = np.zeros(M_LENGTH, dtype=np.int64)
    meta[[M_START, M_RUN, M_COUNT, M_HAS_HEAD, M_N_POS, M_N_EFF, M_SIZE]] = (
        start, run, count, head is not None, n_pos, n_eff, size)
    for at, lay in ((M_HEAD, head), (M_RUN_LAYOUT, layout)):
        if lay is not None:
            meta[at:at + len(LAYOUT_FIELDS)] = [getattr(lay, f) for f in LAYOUT_FIELDS]
    return meta


@njit(cache=True)
def _point(meta, k):
    """(first byte of point k, index of its layout in meta)."""
    head = meta[M_HAS_HEAD]
    if head and k == 0:
        return meta[M_START], M_HEAD
    return meta[M_RUN] + (k - head) * meta[M_SIZE], M_RUN_LAYOUT


@njit(cache=True)
def _words(b):
    """
    `b` (uint8) as uint32 words from byte 0 and as float64 from byte 4.

    CDR aligns every field to its size from the byte after the 4-byte encapsulation header, so
    the counts and stamps of the points are words and their values doubles of these views.
    """
    n4 = b.shape[0] // 4
    n8 = (b.shape[0] - 4) // 8
    return b[:4 * n4].view(np.uint32), b[4:4 + 8 * n8].view(np.float64)


@njit(cache=True)
def read_points(b, meta, t0):
    """
    Read every point of buffer `b` (uint8) of the shape `meta`; header stamp t0 (int ns).

    Returns (ok, stamps (n,) int64 ns, positions (n, n_pos), efforts (n, n_eff)); ok is False,
    the arrays unfinished, when a point's counts are not the shape's (the caller decodes it the
    general way).
    """
    count, n_pos, n_eff = meta[M_COUNT], meta[M_N_POS], meta[M_N_EFF]
    stamps = np.empty(count, dtype=np.int64)
    pos = np.empty((count, n_pos))
    eff = np.empty((count, n_eff))
    words, doubles = _words(b)
    for k in range(count):
        base, lay = _point(meta, k)
        if (words[(base + meta[lay + F_N_POS]) >> 2] != n_pos
                or words[(base + meta[lay + F_N_VEL]) >> 2] != 0
                or words[(base + meta[lay + F_N_ACC]) >> 2] != 0
                or words[(base + meta[lay + F_N_EFF]) >> 2] != n_eff):
            return False, stamps, pos, eff
        sec = np.int64(np.int32(words[(base + meta[lay + F_SEC]) >> 2]))
        nsec = np.int64(words[(base + meta[lay + F_NSEC]) >> 2])
        stamps[k] = sec * 1_000_000_000 + nsec + t0
        at = (base + meta[lay + F_POS] - 4) >> 3
        for j in range(n_pos):
            pos[k, j] = doubles[at + j]
        at = (base + meta[lay + F_EFF] - 4) >> 3
        for j in range(n_eff):
            eff[k, j] = doubles[at + j]
    return True, stamps, pos, eff


@njit(cache=True)
def write_points(o, meta, stamps, t0, pos, eff):
    """
    Write the values and time_from_start of every point into `o` (uint8, a template's copy).

    stamps (n,) int64 ns, t0 the header stamp; time_from_start = stamp - t0 as (int32 sec,
    uint32 nsec) with nsec in [0, 1e9); positions (n, n_pos) and efforts (n, n_eff) float64.
    """
    words, doubles = _words(o)
    for k in range(meta[M_COUNT]):
        base, lay = _point(meta, k)
        d = stamps[k] - t0
        sec = d // 1_000_000_000
        words[(base + meta[lay + F_SEC]) >> 2] = np.uint32(sec & 0xFFFFFFFF)
        words[(base + meta[lay + F_NSEC]) >> 2] = np.uint32(d - sec * 1_000_000_000)
        at = (base + meta[lay + F_POS] - 4) >> 3
        for j in range(pos.shape[1]):
            doubles[at + j] = pos[k, j]
        at = (base + meta[lay + F_EFF] - 4) >> 3
        for j in range(eff.shape[1]):
            doubles[at + j] = eff[k, j]
