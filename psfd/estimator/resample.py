"""Band-limiting and interpolation shared by the estimators.

Both methods low-pass an image by truncating its DCT and then resample it with
Keys' bicubic kernel (a = -0.5) on the s-times grid.
Delbracio et al., IJCV 2012, sec. 4.2 and Delbracio PhD thesis 2013, App. A.1;
Delbracio, Almansa, Morel, Musé, SIAM J. Imaging Sci. 2012, sec. 4 (eq. (17)).
"""

from __future__ import annotations

import cv2
import numpy as np

from psfd.estimator import fourier

__all__ = [
    "band_part_cover", "dct_bases", "dct_coefficients", "dct_lowpass", "dct_runs_part",
    "dct_synthesise", "erode", "keys_bicubic", "keys_grid", "keys_upsample", "keys_weights",
]


def dct_lowpass(
    image: np.ndarray,
    keep: tuple[int, int],
    size: tuple[int, int] | None = None,
    mask: np.ndarray | None = None,
    cross_mask: np.ndarray | None = None,
) -> np.ndarray:
    """Low-pass an image by zeroing its DCT-II coefficients from index ``keep`` on.

    The DCT avoids the ringing a periodic FFT filter would add at the image
    borders (Delbracio PhD thesis 2013, App. A.1: keep indices below
    (m s, n s) for an m x n observed window at factor s).

    Parameters
    ----------
    image : ndarray, 2-D
        float32 input is filtered in float32 (half the work; the filter's
        rounding stays far below sensor noise), anything else in float64.
    keep : (int, int)
        Number of coefficients kept along rows (axis 0) and columns (axis 1).
    size : (int, int), optional
        Resynthesise the kept band on a grid of this shape instead of the
        image's own (a band-limited zoom: sample (i + 0.5) rows / size[0] - 0.5
        of the original grid), with the amplitude preserved.
    mask : ndarray (>= keep[0], >= keep[1]), optional
        Weights (bool or float) of the kept coefficients: a band that is not
        a rectangle. Coefficient (i, j) holds the frequencies (+-i, +-j) of
        the image's half-sample-symmetric extension (the DCT-II's implicit
        periodisation, 2 rows x 2 cols); ``mask`` weighs the pair (i, j),
        (-i, -j).
    cross_mask : ndarray like ``mask``, optional
        Weights of the other pair (i, -j), (-i, j); ``mask`` by default, which
        is a plain weighting of the DCT coefficients. A different cross mask
        filters the symmetric extension with a band that is not symmetric
        under x -> -x (e.g. a rotated square), still without border ringing.

    Returns
    -------
    ndarray of shape ``size`` (default: the shape of ``image``).
    """
    image = np.asarray(image)
    if image.dtype != np.float32:
        image = image.astype(np.float64)
    rows, cols = image.shape
    out_r, out_c = (rows, cols) if size is None else (int(size[0]), int(size[1]))
    keep_r, keep_c = min(int(keep[0]), rows, out_r), min(int(keep[1]), cols, out_c)
    if mask is None and keep_r >= rows and keep_c >= cols and (out_r, out_c) == (rows, cols):
        return image.copy()
    coeffs = dct_coefficients(image, (keep_r, keep_c))
    if mask is not None:
        mask = np.asarray(mask)[:keep_r, :keep_c]
        cross_mask = None if cross_mask is None else np.asarray(cross_mask)[:keep_r, :keep_c]
    lowpassed = dct_synthesise(coeffs, (out_r, out_c), mask, cross_mask)
    if (out_r, out_c) != (rows, cols):
        # orthonormal DCTs of different lengths: sqrt(new / old) keeps the amplitude
        lowpassed *= np.sqrt(out_r * out_c / (rows * cols)).astype(lowpassed.dtype)
    return lowpassed


def dct_coefficients(image: np.ndarray, keep: tuple[int, int]) -> np.ndarray:
    """The orthonormal DCT-II coefficients of ``image`` below index ``keep`` (rows, cols).

    Axis by axis, dropping the unwanted coefficients at once, so the second
    pass works on fewer lines. float32 input stays float32.
    """
    coeffs = fourier.dct(image, int(keep[1]), axis=1)
    return fourier.dct(coeffs, int(keep[0]), axis=0)


def dct_synthesise(
    coeffs: np.ndarray, size: tuple[int, int], mask: np.ndarray | None = None, cross_mask: np.ndarray | None = None
) -> np.ndarray:
    """The image of `dct_coefficients` ``coeffs`` weighted by the band ``mask`` / ``cross_mask`` (see `dct_lowpass`).

    The coefficients the array does not hold are zero; ``size`` is the
    (rows, cols) of the grid to synthesise on (the transform's length).
    """
    out_r, out_c = int(size[0]), int(size[1])
    anti = None
    if mask is not None:
        same = np.asarray(mask, dtype=coeffs.dtype)
        cross = same if cross_mask is None else np.asarray(cross_mask, dtype=coeffs.dtype)
        if same.shape != coeffs.shape or cross.shape != coeffs.shape:
            raise ValueError(f"mask and cross_mask need at least {coeffs.shape} coefficients")
        # With theta = pi i (row + 1/2) / rows, phi = pi j (col + 1/2) / cols,
        # a = mask and b = cross_mask, the pairs of coefficient (i, j) resynthesise
        # (a cos(theta + phi) + b cos(theta - phi)) / 2
        #     = (a + b) / 2 cos(theta) cos(phi) + (b - a) / 2 sin(theta) sin(phi):
        # the cosine part is an inverse DCT-II, the sine part an inverse DST-II
        # (whose index k is frequency k + 1, with the same orthonormal factor).
        if cross is not same and np.any(cross != same):
            anti = (coeffs * (cross - same) / 2)[1:, 1:]
        coeffs = coeffs * (same + cross) / 2
    lowpassed = fourier.idct(fourier.idct(coeffs, out_r, axis=0), out_c, axis=1)
    if anti is not None and anti.size:
        lowpassed += fourier.idst(fourier.idst(anti, out_r, axis=0), out_c, axis=1)
    return lowpassed


def dct_runs_part(
    coeffs: np.ndarray, runs: tuple[np.ndarray, ...], size: tuple[int, int], rows: slice, cols: slice,
    bases: dict | None = None, cover: np.ndarray | None = None,
) -> np.ndarray:
    """The image of runs of DCT coefficients on ``rows`` x ``cols`` of the grid: `dct_synthesise` of a sparse band.

    ``runs`` = (row, start, stop, cos_w, sin_w): coefficients (row[n], start[n] ..
    stop[n] - 1) of ``coeffs`` enter with weight ``cos_w[n]`` on their cosine part
    and ``sin_w[n]`` on their sine part (a band (a, b) of `dct_synthesise` has
    cos_w = (a + b) / 2, sin_w = (b - a) / 2); overlapping runs add up.

    Each part is synthesised from the orthonormal DCT-III and DST-III basis
    functions (sqrt(2 / N) cos(pi k (n + 1/2) / N), sqrt(1 / N) for k = 0;
    sqrt(2 / N) sin(pi k (n + 1/2) / N)) tabulated on the rows and columns
    asked for: B_rows D B_cols^T with D sparse. A coefficient's term is
    separable, so it can reach the image through its row of D
    (B_rows[:, R] (D_R B_cols^T)) or through its column ((B_rows D_C)
    B_cols[:, C]^T); the dense products cost rows x cols x (|R| + |C|),
    so the runs are split between the two to keep R + C small (`_cover`).
    Products and their sums in float32 (the band is read in float32,
    `u_tilde`), and so is the image returned. ``bases`` (`dct_bases` of the
    grid) saves tabulating the basis functions on every call, ``cover``
    (`band_part_cover` of the same runs and crop) choosing the covers again.
    """
    out_r, out_c = int(size[0]), int(size[1])
    n_r = np.arange(out_r)[rows].size
    n_c = np.arange(out_c)[cols].size
    row, start, stop, cos_w, sin_w = (np.asarray(x) for x in runs)
    keep = stop > start
    row, start, stop = row[keep], start[keep], stop[keep]
    weights = {"cos": cos_w[keep].astype(np.float32), "sin": sin_w[keep].astype(np.float32)}
    weights["sin"][row == 0] = 0.0  # sin(0) = 0 on the first row (and column, below)
    weights = {wave: w for wave, w in weights.items() if np.any(w)}
    if row.size == 0 or not weights:
        return np.zeros((n_r, n_c), dtype=np.float32)
    if bases is None:
        bases = {}
        for axis, (n, at) in enumerate(((out_r, np.arange(out_r)[rows]), (out_c, np.arange(out_c)[cols]))):
            bases["cos", axis], bases["sin", axis] = _bases(n, coeffs.shape[axis], at)
        rows = cols = slice(None)
    # (frequency, sample) tables: the frequencies a product needs are rows, read without a gather of columns
    tables = {wave: (bases[wave, 0][:, rows], bases[wave, 1][:, cols]) for wave in weights}
    by_row = _cover(row, start, stop, coeffs.shape, (n_r, n_c))[0] if cover is None else np.asarray(cover)
    # the runs in dense tiles (`_tiles`): runs lo .. hi - 1, rows r0 .. r1 - 1, columns c0 .. c1 - 1
    lo, hi = _tiles(row, start, stop, by_row, (n_r, n_c))
    turned = by_row[lo]
    r0, r1 = row[lo], row[hi - 1] + 1
    c0, c1 = np.minimum.reduceat(start, lo), np.maximum.reduceat(stop, lo)
    count = np.add.reduceat(stop - start, lo)  # coefficients per tile
    # a tile of few coefficients, or mostly empty (scattered coefficients along an edge, as between
    # two nearly equal bands), costs less gathered: its basis functions times their weights, summed
    # per row (column) of D
    scattered = (count < 32) | ((r1 - r0) * (c1 - c0) > 40 * count)
    # the accumulators span the rows (columns) of the dense tiles that reach the image through them; through the
    # rows: N = D B_cols^T, then B_rows[:, R] N[R]; through the columns, kept transposed: M^T = D^T B_rows^T,
    # then M^T[C]^T B_cols[:, C]^T
    dense_rows, dense_cols = turned & ~scattered, ~turned & ~scattered
    row_span = (int(r0[dense_rows].min()), int(r1[dense_rows].max())) if dense_rows.any() else (0, 0)
    col_span = (int(c0[dense_cols].min()), int(c1[dense_cols].max())) if dense_cols.any() else (0, 0)
    through_rows = {wave: np.zeros((row_span[1] - row_span[0], n_c), dtype=np.float32) for wave in weights}
    through_cols = {wave: np.zeros((col_span[1] - col_span[0], n_r), dtype=np.float32) for wave in weights}
    used_rows = np.zeros(row_span[1] - row_span[0], dtype=bool)
    used_cols = np.zeros(col_span[1] - col_span[0], dtype=bool)
    for t in np.flatnonzero(~scattered).tolist():
        # the tile is the box of coefficients times the weights of its runs (one run per row) where they lie
        a0, a1, b0, b1, f0, f1 = int(r0[t]), int(r1[t]), int(c0[t]), int(c1[t]), int(lo[t]), int(hi[t])
        at = np.arange(b0, b1)
        inside = (at >= start[f0:f1, None]) & (at < stop[f0:f1, None])
        if f1 - f0 == a1 - a0:  # a run in every row of the box
            held = (coeffs[a0:a1, b0:b1] * inside).astype(np.float32, copy=False)
            scale = {wave: w[f0:f1, None] for wave, w in weights.items()}
        else:
            held = np.zeros((a1 - a0, b1 - b0), dtype=np.float32)
            held[row[f0:f1] - a0] = coeffs[row[f0:f1], b0:b1] * inside
            scale = {wave: np.zeros((a1 - a0, 1), dtype=np.float32) for wave in weights}
            for wave, w in weights.items():
                scale[wave][row[f0:f1] - a0, 0] = w[f0:f1]
        for wave in weights:
            tile = held * scale[wave]
            if wave == "sin" and b0 == 0:
                tile[:, 0] = 0.0
            table_r, table_c = tables[wave]
            if turned[t]:
                through_rows[wave][a0 - row_span[0]: a1 - row_span[0]] += tile @ table_c[b0:b1]
            else:
                through_cols[wave][b0 - col_span[0]: b1 - col_span[0]] += tile.T @ table_r[a0:a1]
        if turned[t]:
            used_rows[a0 - row_span[0]: a1 - row_span[0]] = True
        else:
            used_cols[b0 - col_span[0]: b1 - col_span[0]] = True
    left, right = [], []
    tile_of = np.repeat(np.arange(lo.size), hi - lo)  # the tile of each run
    for way in (False, True):
        run = np.flatnonzero((scattered & (turned == way))[tile_of])
        if run.size:
            dense = (through_rows, used_rows, row_span[0]) if way else (through_cols, used_cols, col_span[0])
            _scattered_terms(coeffs, (row, start, stop), weights, tables, run, way, dense, (left, right))
    # both parts through both covers as one product: B_rows[:, R] N[R] + M[:, C] B_cols[:, C]^T stacked along
    # the summed index (the same multiply-adds as four products, at the cost of one call)
    for wave in weights:
        table_r, table_c = tables[wave]
        if used_cols.any():
            left.append(through_cols[wave][used_cols])
            right.append(table_c[col_span[0]: col_span[1]][used_cols])
        if used_rows.any():
            left.append(table_r[row_span[0]: row_span[1]][used_rows])
            right.append(through_rows[wave][used_rows])
    if not left:
        return np.zeros((n_r, n_c), dtype=np.float32)
    return np.concatenate(left).T @ np.concatenate(right)


def _scattered_terms(coeffs: np.ndarray, runs: tuple[np.ndarray, ...], weights: dict, tables: dict, run: np.ndarray,
                     way: bool, dense: tuple, factors: tuple[list, list]) -> None:
    """The runs ``run`` of `dct_runs_part`'s scattered tiles, coefficient by coefficient, through their rows of
    D (``way``: N[R] = D_R B_cols^T) or their columns (M^T[C] = D_C^T B_rows^T).

    A row (column) of D that the dense tiles reach already (``dense``: their sums per wave, which rows of them
    are used, the first row's index) takes the sum of its terms there. Any other is a term of the final
    product of its own, appended to its ``factors`` (left, right) as it is: B_rows[:, r] and N[r], or M[:, c]
    and B_cols[:, c]. No accumulator over the span of D's rows and no gathers back from it: between two close
    bands every coefficient is scattered, and those were a fifth of the cost of the corrections.
    """
    row, start, stop = runs
    length = stop[run] - start[run]
    which = np.repeat(run, length)
    j = np.arange(which.size) + np.repeat(start[run] - (np.cumsum(length) - length), length)
    i = row[which]
    kept, summed = (i, j) if way else (j, i)  # D's index kept (columns by columns), the one summed over
    index, order, position = _group_order(kept)
    value = coeffs[i[order], j[order]].astype(np.float32)
    sums_of, used, offset = dense
    at = index - offset
    shared = (at >= 0) & (at < used.size)
    shared[shared] = used[at[shared]]
    alone = ~shared
    for wave, w in weights.items():
        terms = tables[wave][1 if way else 0][summed[order]]
        terms *= (value * w[which[order]])[:, None]  # the sine table's frequency 0 is 0: sin(0) = 0
        sums = _group_sums(terms, position)
        if shared.any():
            sums_of[wave][at[shared]] += sums[shared]
            sums = sums[alone]
        basis = tables[wave][0 if way else 1][index[alone]]
        factors[0].append(basis if way else sums)
        factors[1].append(sums if way else basis)


def _group_order(kept: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The entries of `dct_runs_part`'s scattered coefficients ordered for `_group_sums`: the distinct values of
    ``kept`` (its groups), most entries first, and the order of the entries: the first entry of every group, then
    the second of every group that has one, ... (so that each pass adds a block of consecutive rows to the first
    groups); ``position`` holds where each pass begins, and ends."""
    by_kept = np.argsort(kept, kind="stable")
    value = kept[by_kept]
    new = np.r_[True, value[1:] != value[:-1]]
    first = np.flatnonzero(new)
    counts = np.diff(np.r_[first, value.size])
    group = np.cumsum(new) - 1  # of each entry, in the order by_kept
    place = np.arange(value.size) - first[group]  # its place within its group
    by_count = np.argsort(-counts, kind="stable")
    rank = np.empty(counts.size, dtype=np.intp)
    rank[by_count] = np.arange(counts.size)
    order = by_kept[np.argsort(place * counts.size + rank[group])]
    position = np.r_[0, np.cumsum(np.bincount(place))]
    return value[first][by_count], order, position


def _group_sums(terms: np.ndarray, position: np.ndarray) -> np.ndarray:
    """The sum of the terms of each group, with ``terms`` in `_group_order`'s order (rows of the result in the
    order of its groups).

    Between two close bands most groups hold one or two entries: the groups' sums are built by a few
    additions of consecutive rows (pass p adds the p-th entry of the groups that have one, which are the
    first groups); np.add.at or np.add.reduceat along axis 0 pay per entry or per group, 5-10x more.
    ``terms`` is overwritten, and the result is a view of it.
    """
    sums = terms[position[0]: position[1]]
    for p in range(1, position.size - 1):
        block = terms[position[p]: position[p + 1]]
        sums[: block.shape[0]] += block
    return sums


def _tiles(row: np.ndarray, start: np.ndarray, stop: np.ndarray, by_row: np.ndarray,
           out: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """Consecutive runs of `dct_runs_part` grouped into dense tiles: the [lo, hi) ranges of the run list, as two
    arrays.

    A tile holds runs of nearby rows of one edge (one run per row),
    as many as keep the tile's box at most about twice the coefficients it
    holds (many rows along a near-vertical edge, where the runs stay put),
    or more where a product of a small tile costs less than its call
    (~3e5 multiply-adds in numpy on one core): T rows whose runs move by
    ``shift`` cost (T shift / 2) T ``out`` multiply-adds more than their
    runs, least in all at T^2 = 2 x 3e5 / (shift ``out``). The runs of a
    tile share their cover (``by_row``, `_cover`).
    """
    n = row.size
    new_section = np.ones(n, dtype=bool)
    new_section[1:] = (row[1:] <= row[:-1]) | (row[1:] > row[:-1] + 8) | (by_row[1:] != by_row[:-1])
    section = np.cumsum(new_section) - 1
    length = (stop - start).astype(np.float64)
    shift = np.zeros(n)
    shift[1:] = np.abs(start[1:] - start[:-1]) + np.abs(stop[1:] - stop[:-1])
    shift[new_section] = 0.0
    counts = np.bincount(section)
    mean_length = np.bincount(section, weights=length) / counts
    mean_shift = np.maximum(np.bincount(section, weights=shift) / np.maximum(counts - 1, 1), 1e-9)
    other = np.where(by_row[new_section], out[1], out[0])  # the product's other dimension
    rows_per_tile = np.maximum(2 * mean_length / mean_shift, np.sqrt(6e5 / (mean_shift * other)))
    rows_per_tile = np.clip(np.floor(rows_per_tile), 1, 256).astype(np.intp)
    position = np.arange(n) - np.flatnonzero(new_section)[section]
    tile = position // rows_per_tile[section]
    boundary = np.flatnonzero(new_section | np.r_[True, tile[1:] != tile[:-1]])
    return boundary, np.r_[boundary[1:], n]


def _cover(row: np.ndarray, start: np.ndarray, stop: np.ndarray, shape: tuple[int, int],
           out: tuple[int, int]) -> tuple[np.ndarray, float]:
    """Which runs `dct_runs_part` synthesises through their rows (True) rather than their columns, and the
    multiply-adds of one part (cosine or sine).

    A band difference is made of strips along the edges of two close bands,
    one run per row along each edge (`bernoulli._band_difference`
    lists them edge by edge, rows increasing). A near-vertical edge spans
    many rows and few columns: its columns are the cheaper cover; a
    near-horizontal one the other way round. Each edge is cut into chunks
    of 64 rows (an edge turns at the band's corners), and each chunk goes
    by its rows when it has fewer rows than its runs span columns.
    """
    length = stop - start
    edge = np.cumsum(np.r_[True, row[1:] <= row[:-1]]) - 1  # rows increase along an edge
    chunk = edge * (shape[0] // 64 + 1) + row // 64
    first = np.r_[True, chunk[1:] != chunk[:-1]]
    at = np.flatnonzero(first)
    runs = np.diff(np.r_[at, row.size])
    span = np.maximum.reduceat(stop, at) - np.minimum.reduceat(start, at)
    by_row = np.repeat(runs < span, runs)
    used_rows = np.count_nonzero(np.bincount(row[by_row], minlength=shape[0]))
    edges = np.bincount(start[~by_row], minlength=shape[1] + 1) - np.bincount(stop[~by_row], minlength=shape[1] + 1)
    used_cols = np.count_nonzero(np.cumsum(edges)[: shape[1]])
    cost = (float(out[0]) * out[1] * (used_rows + used_cols) + float(length[~by_row].sum()) * out[0]
            + float(length[by_row].sum()) * out[1])
    return by_row, cost


def band_part_cover(runs: tuple[np.ndarray, ...], rows: int, cols: int,
                    shape: tuple[int, int]) -> tuple[np.ndarray, float]:
    """Which of the (non-empty) runs `dct_runs_part` synthesises through their rows (its ``cover`` argument,
    for a call on the same runs and crop size), and the multiply-adds of that call: ``runs`` of a ``shape``
    box of coefficients on ``rows`` x ``cols`` (both parts)."""
    row, start, stop = (np.asarray(x) for x in runs[:3])
    keep = stop > start
    if not keep.any():
        return np.zeros(0, dtype=bool), 0.0
    by_row, cost = _cover(row[keep], start[keep], stop[keep], shape, (rows, cols))
    return by_row, 2.0 * cost


def dct_bases(size: tuple[int, int], keep: tuple[int, int]) -> dict:
    """The basis functions `dct_runs_part` reads, on every row and column of a ``size`` grid, for the
    frequencies below ``keep``, in float32: {("cos" or "sin", axis): ndarray (keep[axis], size[axis])},
    a frequency per row (the products of `dct_runs_part` read whole frequencies: contiguous rows).

    The phase pi k (2 n + 1) / 2N is reduced modulo 2 pi in integers before it
    is rounded to float32 (error ~5e-7, the float32 rounding of the band
    itself): a float64 cosine of the unreduced phase, up to thousands of
    radians, costs 4x as much.
    """
    (n_r, n_c), (k_r, k_c) = (int(n) for n in size), (int(k) for k in keep)
    if n_r == n_c:  # a square grid: one table serves both axes
        cos, sin = _bases(n_r, max(k_r, k_c))
        return {("cos", 0): cos[:k_r], ("sin", 0): sin[:k_r], ("cos", 1): cos[:k_c], ("sin", 1): sin[:k_c]}
    out = {}
    for axis, (n, k) in enumerate(((n_r, k_r), (n_c, k_c))):
        out["cos", axis], out["sin", axis] = _bases(n, k)
    return out


def _bases(n: int, k: int, at: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """`dct_bases`'s cosine and sine tables (frequency, sample) of one axis of length ``n``, on its samples
    ``at`` (all by default)."""
    at = np.arange(n) if at is None else np.asarray(at)
    # the integer phases k (2 n + 1) in 32 bits where they fit (any raster psfd makes): exact, and half the
    # memory and time of int64 (the table's transient peak: a 3200-sample grid's phases are 19 MB, not 37)
    whole = np.int32 if k * (2 * n + 1) < 2**31 else np.int64
    phase = np.outer(np.arange(k, dtype=whole), 2 * at.astype(whole) + 1)
    phase %= 4 * n
    angle = phase.astype(np.float32)
    del phase
    angle *= np.float32(np.pi / (2 * n))
    scale = np.float32(np.sqrt(2.0 / n))
    cos = np.cos(angle)
    cos *= scale
    cos[0] *= np.float32(np.sqrt(0.5))
    sin = np.sin(angle, out=angle)
    sin *= scale
    return cos, sin


def keys_weights(t: np.ndarray, a: float = -0.5) -> np.ndarray:
    """Keys' cubic convolution weights for the four taps around fractional offset ``t``.

    Keys, IEEE Trans. ASSP 1981, eq. (15); a = -0.5 makes the interpolant
    third-order accurate (the value the reference code was corrected to).

    Parameters
    ----------
    t : ndarray
        Fractional offsets in [0, 1).
    a : float

    Returns
    -------
    ndarray with a trailing axis of 4: weights of taps at offsets -1, 0, 1, 2.
    """
    return np.stack(_keys_taps(np.asarray(t), a), axis=-1)


def keys_upsample(values: np.ndarray, s: int, start: tuple[int, int], shape: tuple[int, int]) -> np.ndarray:
    """A smooth function sampled on integers, interpolated (Keys, a = -0.5) on the grid of step 1 / s.

    ``values[..., r, c]`` is the function at (r - 1 + start[0] // s, c - 1 + start[1] // s)
    (leading axes: several functions on the same grid); the result holds it at (i / s, j / s) for i from
    ``start[0]``, j from ``start[1]``, over ``shape``. ``values`` needs (shape + start % s) / s + 3
    samples along each axis (`keys_grid` gives the integer range). Keys' a = -0.5 kernel
    reproduces quadratics exactly (Keys, IEEE Trans. ASSP 1981, sec. III), so
    a map whose third derivatives are small over one sample (a homography,
    lens distortion) is reproduced to far below its own precision.

    The interpolation is separable and linear: two products with the banded matrices of the taps' weights
    (`_keys_matrix`), axis 0 first (a few small BLAS calls instead of eight passes over shifted views).
    """
    out = np.asarray(values, dtype=np.float64)
    down = _keys_matrix(out.shape[-2], s, start[0], shape[0])
    across = _keys_matrix(out.shape[-1], s, start[1], shape[1])
    return (down @ out) @ across.T


def _keys_matrix(count_in: int, s: int, start: int, count: int) -> np.ndarray:
    """Row i: Keys' weights (`keys_weights`) of the sample (start + i) / s on the integers start // s - 1 ..
    start // s - 1 + count_in - 1 (four of them nonzero), as `keys_upsample` reads them."""
    at = np.arange(count) + start % s
    matrix = np.zeros((count, count_in))
    matrix[np.arange(count)[:, None], (at // s)[:, None] + np.arange(4)] = keys_weights((at % s) / s)
    return matrix


def keys_grid(start: int, count: int, s: int) -> np.ndarray:
    """The integers `keys_upsample` needs to cover samples ``start / s`` .. ``(start + count - 1) / s``."""
    return np.arange(start // s - 1, (start + count - 1) // s + 3)


def keys_bicubic(
    image: np.ndarray,
    x: np.ndarray,
    y: np.ndarray,
    a: float = -0.5,
    fill: float = np.nan,
) -> np.ndarray:
    """Sample ``image`` at real positions with Keys' bicubic interpolation.

    OpenCV's ``remap`` has a fixed a = -0.75, so the a = -0.5 kernel the
    papers specify is evaluated here directly.

    Parameters
    ----------
    image : ndarray, 2-D
        float32 input is interpolated in float32, anything else in float64.
    x, y : ndarray
        Column and row coordinates (pixel centres at integers), same shape.
    a : float
        Keys' parameter.
    fill : float
        Value where the 4 x 4 neighbourhood leaves the image.

    Returns
    -------
    ndarray with the shape of ``x`` and the working precision of ``image``.
    """
    image = np.asarray(image)
    dtype = np.float32 if image.dtype == np.float32 else np.float64
    flat = np.ascontiguousarray(image, dtype=dtype).ravel()
    x = np.asarray(x)
    y = np.asarray(y)
    rows, cols = image.shape
    x0 = np.floor(x)
    y0 = np.floor(y)
    inside = (x0 >= 1) & (x0 <= cols - 3) & (y0 >= 1) & (y0 <= rows - 3)
    if not inside.any():
        return np.full(x.shape, fill, dtype=dtype)
    every = bool(inside.all())  # the usual case: no copies of the samples inside
    xi = (x0 if every else x0[inside]).astype(np.intp)
    yi = (y0 if every else y0[inside]).astype(np.intp)
    wx = _keys_taps(((x if every else x[inside]) - xi).astype(dtype), a)
    wy = _keys_taps(((y if every else y[inside]) - yi).astype(dtype), a)
    # Flat indices into the raveled image: np.take on 1-D is much faster than 2-D fancy indexing. Every tap
    # reads the image from its offset on, at the index of the top-left tap: no index array per tap.
    corner = (yi - 1) * cols + (xi - 1)
    acc = np.zeros(xi.shape, dtype=dtype)
    for j in range(4):
        line = wx[0] * np.take(flat[j * cols:], corner)
        for i in range(1, 4):
            line += wx[i] * np.take(flat[j * cols + i:], corner)
        acc += wy[j] * line
    if every:
        return acc
    out = np.full(x.shape, fill, dtype=dtype)
    out[inside] = acc
    return out


def _keys_taps(t: np.ndarray, a: float) -> tuple[np.ndarray, ...]:
    """`keys_weights` as four arrays of the shape of ``t``, one per tap (each contiguous)."""
    u = 1 - t
    # Keys, IEEE Trans. ASSP 1981, eq. (15) at the distances 1 + t and 2 - t (outer taps) and t, 1 - t (inner),
    # expanded
    return (a * t * u * u, ((a + 2) * t - (a + 3)) * t * t + 1, ((a + 2) * u - (a + 3)) * u * u + 1, a * u * t * t)


def erode(mask: np.ndarray, radius: int) -> np.ndarray:
    """Erode a validity mask by a square of half-size ``radius`` pixels.

    The papers erode the observation mask by (k - 1) / (2 s) pixels so that
    every kept sample sees a full kernel footprint of valid data
    (Delbracio PhD thesis 2013, App. A.1).
    """
    mask = np.ascontiguousarray(mask, dtype=bool)
    if radius <= 0:
        return mask.copy()
    # OpenCV's erosion (outside the image counts as invalid): scipy.ndimage would add 0.1 s of imports
    structure = np.ones((2 * radius + 1, 2 * radius + 1), dtype=np.uint8)
    eroded = cv2.erode(mask.view(np.uint8), structure, borderType=cv2.BORDER_CONSTANT, borderValue=0)
    return eroded.view(bool)
