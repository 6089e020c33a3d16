"""Building blocks of the second world generator (``worlds_alt.py``): the raster being built,
terrain by midpoint displacement, roads, buildings, crowns, the lit orthoimage and Foerstner
corners."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage

BASE_HEIGHT_M = 300.0


@dataclass(eq=False)
class Canvas:
    """The raster being built: cell centres in local metres, rows southwards."""

    n: int
    cell: float
    rng: np.random.Generator
    dtm: np.ndarray = field(init=False)
    above: np.ndarray = field(init=False)  # building height above ground
    canopy: np.ndarray = field(init=False)  # vegetation height above ground
    albedo: np.ndarray = field(init=False)
    water: np.ndarray = field(init=False)
    roads: np.ndarray = field(init=False)

    def __post_init__(self) -> None:
        shape = (self.n, self.n)
        self.dtm = np.zeros(shape)
        self.above = np.zeros(shape, np.float32)
        self.canopy = np.zeros(shape, np.float32)
        self.albedo = np.full(shape, 0.5, np.float32)
        self.water = np.zeros(shape, bool)
        self.roads = np.zeros(shape, bool)

    @property
    def half(self) -> float:
        return self.n * self.cell / 2

    @property
    def area_km2(self) -> float:
        return (self.n * self.cell / 1000) ** 2

    def xy(self, rows, cols):
        return -self.half + (np.asarray(cols) + 0.5) * self.cell, \
            self.half - (np.asarray(rows) + 0.5) * self.cell

    def grid_xy(self):
        c = -self.half + (np.arange(self.n) + 0.5) * self.cell
        return c[None, :], -c[:, None]  # x varies along columns, y decreases along rows

    def free(self) -> np.ndarray:
        return (self.above <= 0) & ~self.roads & ~self.water


# ------------------------------------------------------------------------------------ terrain
def diamond_square(k: int, hurst: float, rng: np.random.Generator) -> np.ndarray:
    """A (2^k + 1)^2 field of fractional Brownian motion by midpoint displacement, unit std."""
    n = 2**k + 1
    z = np.zeros((n, n))
    z[:: n - 1, :: n - 1] = rng.normal(size=(2, 2))
    step, amp = n - 1, 1.0
    while step > 1:
        h = step // 2
        amp *= 0.5**hurst
        corners = (z[:-1:step, :-1:step] + z[:-1:step, step::step] + z[step::step, :-1:step]
                   + z[step::step, step::step])
        z[h::step, h::step] = corners / 4 + amp * rng.normal(size=corners.shape)
        pad = np.pad(z, h, constant_values=np.nan)
        for r0, c0 in ((h, 0), (0, h)):  # the edge midpoints: their neighbours are all set
            rr, cc = np.meshgrid(np.arange(r0, n, step), np.arange(c0, n, step), indexing="ij")
            nb = np.stack([pad[rr, cc + h], pad[rr + 2 * h, cc + h], pad[rr + h, cc],
                           pad[rr + h, cc + 2 * h]])
            z[rr, cc] = np.nanmean(nb, axis=0) + amp * rng.normal(size=rr.shape)
        step = h
    return (z - z.mean()) / z.std()


def fbm(n: int, hurst: float, rng: np.random.Generator, *, max_k: int = 10) -> np.ndarray:
    """Midpoint-displacement field resampled (bilinear) onto an ``n`` x ``n`` raster."""
    k = int(min(max_k, max(3, np.ceil(np.log2(max(n - 1, 2))))))
    z = diamond_square(k, hurst, rng)
    t = np.linspace(0, z.shape[0] - 1, n)
    return ndimage.map_coordinates(z, np.meshgrid(t, t, indexing="ij"), order=1)


def _cubic_weights(n: int, cell: float, wavelength_m: float, m: int):
    """Sparse (n, m) Catmull-Rom weights that interpolate a lattice ``wavelength_m`` apart at
    ``n`` cell centres."""
    from scipy import sparse

    t = (np.arange(n) + 0.5) * cell / wavelength_m + 1.0
    i0 = np.floor(t).astype(int)
    f = t - i0
    w = np.stack([((-f + 2) * f - 1) * f / 2, ((3 * f - 5) * f * f + 2) / 2,
                  ((-3 * f + 4) * f + 1) * f / 2, (f - 1) * f * f / 2], axis=1)
    cols = np.clip(i0[:, None] + np.arange(-1, 3)[None, :], 0, m - 1)
    return sparse.csr_matrix((w.ravel(), (np.repeat(np.arange(n), 4), cols.ravel())), (n, m))


def value_noise(n: int, cell: float, wavelength_m: float, rng: np.random.Generator
                ) -> np.ndarray:
    """Random values on a lattice ``wavelength_m`` apart, interpolated by cubic convolution
    (separably, as two sparse products); unit standard deviation."""
    m = int(np.ceil(n * cell / wavelength_m)) + 4
    lattice = rng.normal(size=(m, m))
    W = _cubic_weights(n, cell, wavelength_m, m)
    out = W @ (W @ lattice.T).T
    return (out / max(out.std(), 1e-9)).astype(np.float32)


def smooth(a: np.ndarray, sigma_m: float, cell: float) -> np.ndarray:
    """A Gaussian blur of ``sigma_m`` metres, done on a decimated copy when it is wide."""
    sigma = sigma_m / cell
    f = max(1, int(sigma / 4))
    if f == 1:
        return ndimage.gaussian_filter(a, sigma)
    n0, n1 = a.shape
    small = a[: n0 // f * f, : n1 // f * f].reshape(n0 // f, f, n1 // f, f).mean(axis=(1, 3))
    small = ndimage.gaussian_filter(small, sigma / f, mode="nearest")
    r = np.clip((np.arange(n0) + 0.5) / f - 0.5, 0, small.shape[0] - 1)
    c = np.clip((np.arange(n1) + 0.5) / f - 0.5, 0, small.shape[1] - 1)
    return ndimage.map_coordinates(small, np.meshgrid(r, c, indexing="ij"), order=1)


def carve_valleys(c: Canvas, depth_m: float, width: float, hurst: float) -> None:
    """V-shaped valleys along the zero lines of another field (a network of sinuous lines)."""
    f = fbm(c.n, hurst, c.rng)
    c.dtm -= depth_m * np.exp(-((f / width) ** 2))


def terraces(c: Canvas, step_m: float, where: np.ndarray) -> None:
    """Steps of ``step_m`` with smooth risers where ``where`` holds (vineyard slopes)."""
    z = c.dtm / step_m
    frac = z - np.floor(z)
    riser = np.clip((frac - 0.75) / 0.25, 0, 1)
    stepped = (np.floor(z) + riser * riser * (3 - 2 * riser)) * step_m
    c.dtm = np.where(where, stepped, c.dtm)


def lakes(c: Canvas, share: float, min_area_m2: float) -> None:
    """Flood the lowest ``share`` of basins: flat water at the spill level of each lake."""
    smoothed = smooth(c.dtm, 30.0, c.cell)
    low = smoothed < np.quantile(smoothed, share)
    labels, k = ndimage.label(low)
    if k == 0:
        return
    sizes = ndimage.sum(low, labels, np.arange(1, k + 1)) * c.cell**2
    for i in np.flatnonzero(sizes >= min_area_m2)[:6] + 1:
        lake = labels == i
        level = float(np.percentile(c.dtm[lake], 60))
        lake &= c.dtm <= level + 0.5
        c.dtm[lake] = level
        c.water |= lake


# -------------------------------------------------------------------------------------- roads
def _walk(c: Canvas, start, heading, length_m, wiggle_deg) -> np.ndarray:
    """A random-walk polyline (x, y) with steps of half a cell."""
    step = c.cell / 2
    k = int(length_m / step)
    turns = np.cumsum(c.rng.normal(0, np.radians(wiggle_deg) * np.sqrt(step / 10), k))
    ang = heading + ndimage.gaussian_filter1d(turns, 40)
    xy = np.asarray(start) + np.cumsum(np.column_stack([np.cos(ang), np.sin(ang)]) * step, 0)
    inside = np.all(np.abs(xy) < c.half - c.cell, axis=1)
    return xy[inside]


def _mark(c: Canvas, lines: list[np.ndarray]) -> np.ndarray:
    centre = np.zeros((c.n, c.n), bool)
    for xy in lines:
        if len(xy):
            rows = ((c.half - xy[:, 1]) / c.cell).astype(int)
            cols = ((xy[:, 0] + c.half) / c.cell).astype(int)
            centre[rows, cols] = True
    return centre


def lay_roads(c: Canvas, lines: list[np.ndarray], half_width_m: float, *, bank_m: float = 8.0,
              embank: bool = True, grey: float = 0.32) -> np.ndarray:
    """Roads along ``lines``: the surface follows the terrain smoothed over ~100 m, so it runs on
    embankments across hollows and in cuttings through rises; returns the road mask."""
    centre = _mark(c, lines)
    if not centre.any():
        return centre
    dist, (ir, ic) = ndimage.distance_transform_edt(~centre, return_indices=True)
    dist *= c.cell
    road = dist <= half_width_m
    if embank:
        level = smooth(c.dtm, 50.0, c.cell)[ir, ic]
        t = np.clip((dist - half_width_m) / bank_m, 0, 1)
        near = dist <= half_width_m + bank_m
        c.dtm = np.where(near, level * (1 - t) + c.dtm * t, c.dtm)
    c.roads |= road & ~c.water
    c.albedo[road] = grey
    return road


def random_roads(c: Canvas, count: int, length_m: tuple[float, float], wiggle_deg: float
                 ) -> list[np.ndarray]:
    return [_walk(c, c.rng.uniform(-c.half, c.half, 2), c.rng.uniform(0, 2 * np.pi),
                  c.rng.uniform(*length_m), wiggle_deg) for _ in range(count)]


# ---------------------------------------------------------------------------------- buildings
ROOF_GREYS = (0.28, 0.36, 0.45, 0.55, 0.68, 0.8)


def stamp_building(c: Canvas, cx: float, cy: float, length: float, width: float, angle: float,
                   height: float, roof: str, *, ridge_m: float = 3.0,
                   grey: float | None = None) -> bool:
    """A building footprint of ``length`` x ``width`` metres; ``roof``: flat, gable, hip, shed,
    sawtooth or barrel. False (nothing stamped) where it would hit a road, water or another
    building, or leave the world."""
    r = 0.5 * np.hypot(length, width)
    rows = slice(int((c.half - cy - r) / c.cell), int((c.half - cy + r) / c.cell) + 1)
    cols = slice(int((cx + c.half - r) / c.cell), int((cx + c.half + r) / c.cell) + 1)
    if rows.start < 0 or cols.start < 0 or rows.stop > c.n or cols.stop > c.n:
        return False
    x, y = c.xy(np.arange(rows.start, rows.stop)[:, None], np.arange(cols.start, cols.stop)[None])
    u = np.cos(angle) * (x - cx) + np.sin(angle) * (y - cy)
    v = -np.sin(angle) * (x - cx) + np.cos(angle) * (y - cy)
    inside = (np.abs(u) < length / 2) & (np.abs(v) < width / 2)
    if not inside.any():
        return False
    blocked = c.roads[rows, cols] | c.water[rows, cols] | (c.above[rows, cols] > 0)
    if blocked[inside].any():
        return False
    au, av = 1 - np.abs(u) / (length / 2), 1 - np.abs(v) / (width / 2)
    if roof == "gable":
        z = height + ridge_m * av
    elif roof == "hip":
        z = height + ridge_m * np.minimum(av, au * length / width)
    elif roof == "shed":
        z = height + ridge_m * (v / width + 0.5)
    elif roof == "sawtooth":
        z = height + ridge_m * ((u / 8.0) % 1.0)
    elif roof == "barrel":
        z = height + ridge_m * np.sqrt(np.clip(1 - (v / (width / 2)) ** 2, 0, 1))
    else:
        z = np.full(u.shape, height)
    g = grey if grey is not None else c.rng.choice(ROOF_GREYS) + c.rng.uniform(-0.04, 0.04)
    c.above[rows, cols] = np.where(inside, z, c.above[rows, cols])
    c.albedo[rows, cols] = np.where(inside, g, c.albedo[rows, cols])
    return True


def houses_along(c: Canvas, lines: list[np.ndarray], *, spacing_m: tuple[float, float],
                 setback_m: float, size_m: tuple[float, float], storeys: tuple[int, int],
                 roofs: tuple[str, ...]) -> None:
    """Detached houses on both sides of each street, turned to face it."""
    for xy in lines:
        if len(xy) < 10:
            continue
        s = np.concatenate([[0], np.cumsum(np.hypot(*np.diff(xy, axis=0).T))])
        at = np.arange(c.rng.uniform(0, spacing_m[1]), s[-1], c.rng.uniform(*spacing_m))
        for a in at:
            i = min(int(np.searchsorted(s, a)), len(xy) - 2)
            d = xy[i + 1] - xy[i]
            ang = np.arctan2(d[1], d[0])
            normal = np.array([-np.sin(ang), np.cos(ang)])
            for side in (-1, 1):
                w, ln = np.sort(c.rng.uniform(*size_m, 2))
                p = xy[i] + side * normal * (setback_m + w / 2 + c.rng.uniform(-2, 2))
                h = 3.0 * c.rng.integers(storeys[0], storeys[1] + 1) + 0.5
                stamp_building(c, p[0], p[1], ln, w, ang + c.rng.normal(0, 0.04), h,
                               str(c.rng.choice(roofs)), ridge_m=c.rng.uniform(2.5, 5.0))


def cluster(c: Canvas, centre, count: int, spread_m: float, size_m, height_m, roofs) -> None:
    """Buildings scattered around ``centre``, sharing one orientation (a farmstead, a hamlet)."""
    ang = c.rng.uniform(0, np.pi)
    for _ in range(count):
        p = np.asarray(centre) + c.rng.normal(0, spread_m, 2)
        w, ln = np.sort(c.rng.uniform(*size_m, 2))
        stamp_building(c, p[0], p[1], ln, w, ang + c.rng.choice([0, np.pi / 2]),
                       c.rng.uniform(*height_m), str(c.rng.choice(roofs)),
                       ridge_m=c.rng.uniform(2, 5))


# ------------------------------------------------------------------------------------- crowns
def _nearest_two(c: Canvas, spacing_m: float, jitter: float):
    """Worley features on a jittered lattice: distances to the nearest and second seed and the
    nearest seed's id, for every cell."""
    x, y = c.grid_xy()
    m = int(np.ceil(c.n * c.cell / spacing_m)) + 2
    sx = (np.arange(m)[None, :] + 0.5 + c.rng.uniform(-jitter, jitter, (m, m))) * spacing_m
    sy = (np.arange(m)[:, None] + 0.5 + c.rng.uniform(-jitter, jitter, (m, m))) * spacing_m
    gx, gy = x + c.half, y + c.half  # from the lower-left corner
    ix = np.broadcast_to((gx // spacing_m).astype(int), (c.n, c.n))
    iy = np.broadcast_to((gy // spacing_m).astype(int), (c.n, c.n))
    d1 = np.full((c.n, c.n), np.inf, np.float32)
    d2 = d1.copy()
    ids = np.zeros((c.n, c.n), np.int64)
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            jy, jx = np.clip(iy + dy, 0, m - 1), np.clip(ix + dx, 0, m - 1)
            d = np.hypot(gx - sx[jy, jx], gy - sy[jy, jx]).astype(np.float32)
            closer = d < d1
            d2 = np.where(closer, d1, np.minimum(d2, d))
            ids = np.where(closer, jy * m + jx, ids)
            d1 = np.where(closer, d, d1)
    return d1, d2, ids


def crowns(c: Canvas, where: np.ndarray, *, spacing_m: float, height_m: tuple[float, float],
           radius_per_height: float, profile: str = "cone", jitter: float = 0.4,
           angle: float = 0.0, keep: float = 1.0, albedo: float = 0.24) -> None:
    """Tree crowns (cones or domes on a short trunk) seeded on a lattice ``spacing_m`` apart
    turned by ``angle`` (jitter 0: rows, an orchard), alive where ``where`` holds at the seed;
    each cell takes its highest crown. Crowns are splatted offset by offset over all seeds."""
    ca, sa = np.cos(angle), np.sin(angle)
    m = int(np.ceil(np.sqrt(2) * c.n * c.cell / spacing_m)) + 4
    g = np.arange(m) + 0.5 - m / 2
    su = (g[None, :] + c.rng.uniform(-jitter, jitter, (m, m))) * spacing_m
    sv = (g[:, None] + c.rng.uniform(-jitter, jitter, (m, m))) * spacing_m
    h = c.rng.uniform(*height_m, (m, m))
    sx, sy = (ca * su - sa * sv).ravel(), (sa * su + ca * sv).ravel()
    col, row = (sx + c.half) / c.cell, (c.half - sy) / c.cell
    c0, r0 = np.floor(col).astype(int), np.floor(row).astype(int)
    inside = (c0 >= 0) & (c0 < c.n) & (r0 >= 0) & (r0 < c.n)
    alive = inside & (c.rng.random(m * m) < keep)
    alive[alive] = where[r0[alive], c0[alive]]
    _, first = np.unique(r0[alive] * c.n + c0[alive], return_index=True)  # one seed a cell
    pick = np.flatnonzero(alive)[first]
    col, row, c0, r0, h = col[pick], row[pick], c0[pick], r0[pick], h.ravel()[pick]
    rad = radius_per_height * h
    reach = int(np.ceil(radius_per_height * height_m[1] / c.cell))
    out = np.zeros(c.n * c.n, np.float32)
    for dr in range(-reach, reach + 1):
        for dc in range(-reach, reach + 1):
            rr, cc = r0 + dr, c0 + dc
            d = np.hypot(cc + 0.5 - col, rr + 0.5 - row) * c.cell / rad
            ok = (d < 1) & (rr >= 0) & (rr < c.n) & (cc >= 0) & (cc < c.n)
            dd = d[ok]
            shape = 1 - dd if profile == "cone" else np.sqrt(1 - dd * dd)
            idx = rr[ok] * c.n + cc[ok]
            out[idx] = np.maximum(out[idx], h[ok] * (0.35 + 0.65 * shape))
    out = out.reshape(c.n, c.n)
    out[~c.free()] = 0
    grow = out > 1.0
    c.canopy = np.maximum(c.canopy, np.where(grow, out, 0))
    c.albedo[grow] = albedo


# -------------------------------------------------------------------------------------- ortho
def _shift(a: np.ndarray, dr: int, dc: int, fill: float) -> np.ndarray:
    """``out[r, c] = a[r + dr, c + dc]``, ``fill`` outside."""
    out = np.full_like(a, fill)
    n0, n1 = a.shape
    out[max(0, -dr):n0 - max(0, dr), max(0, -dc):n1 - max(0, dc)] = \
        a[max(0, dr):n0 - max(0, -dr), max(0, dc):n1 - max(0, -dc)]
    return out


def cast_shadow(dsm: np.ndarray, cell: float, azimuth_deg: float, elevation_deg: float,
                reach_m: float = 200.0) -> np.ndarray:
    """Cells that the surface hides from the sun: march towards it on growing steps."""
    az = np.radians(azimuth_deg)
    toward = np.array([-np.cos(az), np.sin(az)])  # (rows, cols) towards the sun: north = -row
    rise = np.tan(np.radians(elevation_deg))
    shadow = np.zeros(dsm.shape, bool)
    k = 1.0
    while k * cell <= reach_m:
        dr, dc = np.rint(toward * k).astype(int)
        dist = np.hypot(dr, dc) * cell
        shadow |= _shift(dsm, int(dr), int(dc), -np.inf) > dsm + dist * rise + 0.3
        k = k + 1 if k < 8 else k * 1.25
    return shadow


def render(c: Canvas, dsm: np.ndarray, *, sun_azimuth_deg: float, sun_elevation_deg: float,
           noise: float = 0.012) -> np.ndarray:
    """Grey levels: albedo x (ambient + direct light off the surface normal, not in shadow)."""
    gr, gc = np.gradient(dsm, c.cell)  # rows point south: dz/dy = -gr
    az, el = np.radians(sun_azimuth_deg), np.radians(sun_elevation_deg)
    sun = np.array([np.sin(az) * np.cos(el), np.cos(az) * np.cos(el), np.sin(el)])
    lambert = np.clip((-gc * sun[0] + gr * sun[1] + sun[2]) / np.sqrt(1 + gc**2 + gr**2), 0, 1)
    shadow = cast_shadow(dsm, c.cell, sun_azimuth_deg, sun_elevation_deg)
    light = 0.3 + 0.85 * lambert * ~shadow
    grey = c.albedo * light
    grey = ndimage.gaussian_filter(grey, 0.5) + c.rng.normal(0, noise, grey.shape)
    return np.clip(grey, 0, 1).astype(np.float32)


def foerstner_corners(image: np.ndarray, *, sigma: float = 1.2, min_roundness: float = 0.4,
                      threshold_rel: float = 0.6, window: int = 5):
    """Corners by the Foerstner operator: the size of the error ellipse of a point located by
    the image gradients around it, ``w = det(N) / trace(N)`` of the smoothed structure tensor
    ``N``, kept where the ellipse is round enough (``q = 4 det / trace^2``), stronger than
    ``threshold_rel`` x the mean ``w`` and the largest in a ``window`` x ``window``
    neighbourhood. Returns ``(rows, cols)`` as a (K, 2) array and the weights ``w``."""
    img = image.astype(np.float64)
    gr, gc = ndimage.sobel(img, 0) / 8, ndimage.sobel(img, 1) / 8
    a = ndimage.gaussian_filter(gc * gc, sigma)
    b = ndimage.gaussian_filter(gr * gr, sigma)
    ab = ndimage.gaussian_filter(gc * gr, sigma)
    det, tr = a * b - ab * ab, a + b + 1e-12
    w, q = det / tr, 4 * det / tr**2
    good = (q > min_roundness) & (w > threshold_rel * w.mean())
    peak = good & (w == ndimage.maximum_filter(w, size=window))
    peak[:3, :] = peak[-3:, :] = peak[:, :3] = peak[:, -3:] = False
    rc = np.argwhere(peak)
    return rc, w[rc[:, 0], rc[:, 1]]
