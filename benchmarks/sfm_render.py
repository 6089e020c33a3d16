"""Aerial image blocks rendered from a surface: a DSM and an orthoimage on the same grid.

A block is a few parallel strips flown in alternate directions with a frame camera looking
nearly straight down (a few degrees of roll, pitch and yaw noise). The camera is a pinhole with
two radial distortion coefficients (COLMAP's ``RADIAL`` model, principal point at the image
centre). Every pixel's ray, through the distorted camera, is cast onto the DSM's bilinear
surface (the first hit from above, so roofs hide what is behind them) and the orthoimage is read
there, bilinearly.

Ray casting marches down each ray in steps that cannot pass through the surface: from a point
``f`` above the surface, with a gradient bound ``L`` of the surface within ``R`` cells, the ray
may descend ``min(f / (1 + L tau), R cell / tau)`` (``tau``: horizontal run per unit of descent).
Bounds at several radii are kept (the largest step any of them allows is safe), so steps are
long over flat ground or high above it and short beside walls. All rays of an image advance
together (numpy); an image of 1024 x 768 pixels takes about a second.

Frames: world coordinates are the :class:`~tiereg.simulate.world.World`'s (x east, y north,
z up, one unit a metre, or a foot for a world in feet); cameras follow COLMAP (x right, y down,
z forward; ``x_cam = R_cam_world (X - centre)``); pixel centres at half-integer coordinates,
the image's upper-left corner at (0, 0).
"""

from __future__ import annotations

import logging
from dataclasses import dataclass, field

import numpy as np
from scipy import ndimage

log = logging.getLogger(__name__)

__all__ = ["Camera", "FlightPlan", "HeightField", "Pose", "Texture", "cast_pixels", "make_texture",
           "plan_block", "render_image"]


@dataclass(frozen=True)
class Camera:
    """A pinhole camera with radial distortion (COLMAP ``RADIAL``: f, cx, cy, k1, k2)."""

    width_px: int = 1024
    height_px: int = 768
    focal_px: float = 1100.0
    k1: float = -0.06
    k2: float = 0.015

    @property
    def principal_point(self) -> tuple[float, float]:
        return self.width_px / 2.0, self.height_px / 2.0

    def distort(self, x: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Ideal normalised coordinates -> distorted normalised coordinates."""
        r2 = x * x + y * y
        g = 1.0 + self.k1 * r2 + self.k2 * r2 * r2
        return x * g, y * g

    def undistort(self, xd: np.ndarray, yd: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Distorted -> ideal normalised coordinates (fixed-point iteration; exact to 1e-12 in
        the image for the small coefficients used here)."""
        x, y = xd.copy(), yd.copy()
        for _ in range(30):
            r2 = x * x + y * y
            g = 1.0 + self.k1 * r2 + self.k2 * r2 * r2
            x_new, y_new = xd / g, yd / g
            if max(np.abs(x_new - x).max(initial=0), np.abs(y_new - y).max(initial=0)) < 1e-13:
                return x_new, y_new
            x, y = x_new, y_new
        return x, y

    def rays(self, u_px: np.ndarray, v_px: np.ndarray) -> np.ndarray:
        """(N, 3) directions in the camera frame (z = 1) of the pixels at ``(u, v)``."""
        cx, cy = self.principal_point
        x, y = self.undistort((np.asarray(u_px, float) - cx) / self.focal_px,
                              (np.asarray(v_px, float) - cy) / self.focal_px)
        return np.column_stack([x, y, np.ones_like(x)])

    def project(self, x_cam: np.ndarray) -> np.ndarray:
        """(N, 2) pixel coordinates of camera-frame points (in front of the camera)."""
        xd, yd = self.distort(x_cam[:, 0] / x_cam[:, 2], x_cam[:, 1] / x_cam[:, 2])
        cx, cy = self.principal_point
        return np.column_stack([xd * self.focal_px + cx, yd * self.focal_px + cy])


@dataclass(frozen=True, eq=False)
class Pose:
    """Where an image was taken: ``x_cam = R_cam_world @ (X - centre)``."""

    name: str
    centre: np.ndarray = field(repr=False)
    R_cam_world: np.ndarray = field(repr=False)

    def world_rays(self, camera: Camera, u_px: np.ndarray, v_px: np.ndarray) -> np.ndarray:
        """(N, 3) unit ray directions in the world frame."""
        d = camera.rays(u_px, v_px) @ self.R_cam_world  # = (R^T d_cam^T)^T
        return d / np.linalg.norm(d, axis=1, keepdims=True)

    def to_camera(self, xyz: np.ndarray) -> np.ndarray:
        return (np.asarray(xyz) - self.centre) @ self.R_cam_world.T


@dataclass(frozen=True)
class FlightPlan:
    """A block of ``strips`` x ``images_per_strip`` near-nadir images at ground sampling distance
    ``gsd`` (world units per pixel at the block's median ground height). The long image side
    runs across the flight direction; strips alternate direction."""

    strips: int = 3
    images_per_strip: int = 6
    gsd: float = 1.0
    forward_overlap: float = 0.7
    side_overlap: float = 0.3
    heading_deg: float = 0.0  # flight direction of the first strip, clockwise from north
    attitude_sigma_deg: tuple[float, float, float] = (2.0, 2.0, 3.0)  # roll, pitch, yaw
    position_sigma: float = 0.02  # of the image footprint, horizontally and of the height

    def extent(self, camera: Camera) -> tuple[float, float]:
        """(along, across) ground extent of the planned block in world units."""
        along = camera.height_px * self.gsd
        across = camera.width_px * self.gsd
        return ((self.images_per_strip - 1) * (1 - self.forward_overlap) * along + along,
                (self.strips - 1) * (1 - self.side_overlap) * across + across)


def _rotation_xyz(rx: float, ry: float, rz: float) -> np.ndarray:
    """Rz @ Ry @ Rx of angles in radians."""
    cx, sx, cy, sy, cz, sz = np.cos(rx), np.sin(rx), np.cos(ry), np.sin(ry), np.cos(rz), np.sin(rz)
    Rx = np.array([[1, 0, 0], [0, cx, -sx], [0, sx, cx]])
    Ry = np.array([[cy, 0, sy], [0, 1, 0], [-sy, 0, cy]])
    Rz = np.array([[cz, -sz, 0], [sz, cz, 0], [0, 0, 1]])
    return Rz @ Ry @ Rx


def plan_block(plan: FlightPlan, camera: Camera, *, centre_xy: tuple[float, float],
               ground_z: float, rng: np.random.Generator) -> list[Pose]:
    """Camera poses of the block centred on ``centre_xy``, flown ``gsd * focal`` above
    ``ground_z``; names ``s{strip}_{image}.png`` in flight order."""
    h = np.radians(plan.heading_deg)
    d = np.array([np.sin(h), np.cos(h), 0.0])  # along track (heading clockwise from north)
    n = np.array([d[1], -d[0], 0.0])  # right of the first strip's flight direction
    base = (1 - plan.forward_overlap) * camera.height_px * plan.gsd
    spacing = (1 - plan.side_overlap) * camera.width_px * plan.gsd
    height = plan.gsd * camera.focal_px
    sigma_xy = plan.position_sigma * camera.height_px * plan.gsd
    poses = []
    for s in range(plan.strips):
        forward = d if s % 2 == 0 else -d
        right = np.cross(forward, [0.0, 0.0, 1.0])  # x of the image: right of the flight
        y_axis = -forward  # image down = backwards
        R_nominal = np.array([right, y_axis, [0.0, 0.0, -1.0]])
        v = (s - (plan.strips - 1) / 2) * spacing
        for k in range(plan.images_per_strip):
            u = (k - (plan.images_per_strip - 1) / 2) * base
            u = u if s % 2 == 0 else -u
            centre = (np.array([centre_xy[0], centre_xy[1], ground_z + height])
                      + u * d + v * n)
            centre = centre + rng.normal(0, [sigma_xy, sigma_xy, plan.position_sigma * height])
            roll, pitch, yaw = np.radians(rng.normal(0, plan.attitude_sigma_deg))
            R = _rotation_xyz(pitch, roll, yaw) @ R_nominal  # small turn in the camera frame
            poses.append(Pose(f"s{s}_{k:02d}.png", centre, R))
    return poses


class HeightField:
    """The bilinear surface through a DSM's cell centres, and first hits of rays on it."""

    RADII = (1, 6, 40, 250)  # cells: gradient bounds kept at these radii

    def __init__(self, dsm: np.ndarray, *, x0: float, y0: float, cell: float) -> None:
        self.h = np.asarray(dsm, dtype=np.float64)
        self.x0, self.y0, self.cell = float(x0), float(y0), float(cell)
        h = self.h
        dx = np.abs(np.diff(h, axis=1)) / cell  # (r, c-1)
        dy = np.abs(np.diff(h, axis=0)) / cell  # (r-1, c)
        gx = np.maximum(dx[:-1], dx[1:])
        gy = np.maximum(dy[:, :-1], dy[:, 1:])
        patch = np.hypot(gx, gy).astype(np.float32)  # gradient bound per bilinear patch
        self.bounds = [ndimage.maximum_filter(patch, size=2 * r + 1, mode="nearest")
                       for r in self.RADII]
        top = np.maximum(np.maximum(h[:-1, :-1], h[1:, :-1]), np.maximum(h[:-1, 1:], h[1:, 1:]))
        top = (top + 1e-3 * max(1.0, np.abs(h).max() * 1e-4)).astype(np.float32)  # round up
        self.tops = [ndimage.maximum_filter(top, size=2 * r + 1, mode="nearest")
                     for r in self.RADII]  # highest surface within r patches
        self.z_max = float(h.max())
        self.z_min = float(h.min())

    def _patch(self, x: np.ndarray, y: np.ndarray):
        cf = (x - self.x0) / self.cell - 0.5
        rf = (self.y0 - y) / self.cell - 0.5
        rows, cols = self.h.shape
        inside = (cf >= 0) & (cf < cols - 1) & (rf >= 0) & (rf < rows - 1)
        c = np.clip(np.floor(cf), 0, cols - 2).astype(np.intp)
        r = np.clip(np.floor(rf), 0, rows - 2).astype(np.intp)
        return r, c, rf - r, cf - c, inside

    def height(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        """Bilinear heights; NaN outside the grid of cell centres."""
        r, c, fr, fc, inside = self._patch(np.asarray(x, float), np.asarray(y, float))
        return np.where(inside, self._bilinear_at(r, c, fr, fc), np.nan)

    def intersect(self, origin: np.ndarray, directions: np.ndarray, *, tol: float | None = None,
                  start: np.ndarray | None = None, max_steps: int = 200) -> np.ndarray:
        """(N, 3) first hits of the rays ``origin + t d`` (``d`` pointing down) on the surface;
        NaN rows for rays that leave the grid or point up. ``tol``: height above the surface at
        which a ray counts as arrived (default 0.005 cell). ``start``: per ray, the drop below
        the origin down to which the ray is known to be clear of the surface (default: down to
        the DSM's top).

        Each ray descends by the longest step its height and gradient bounds allow (the highest
        surface and the steepest slope within a few radii are kept), or by a Newton step on
        its height above the surface (at most a cell sideways) if that is longer; a step
        that ends below the surface brackets the hit, which false position then finds. Only a
        wedge of surface thinner than a cell can be stepped over."""
        tol = 5e-3 * self.cell if tol is None else tol
        d = np.asarray(directions, dtype=np.float64)
        o = np.asarray(origin, dtype=np.float64)
        out = np.full((len(d), 3), np.nan)
        down = d[:, 2] < -1e-9
        v = np.zeros_like(d)
        v[down] = d[down] / -d[down, 2:3]  # per unit of drop: (vx, vy, -1)
        tau = np.hypot(v[:, 0], v[:, 1])
        s = np.full(len(d), max(0.0, o[2] - self.z_max))  # drop below the origin
        if start is not None:
            s = np.maximum(s, np.nan_to_num(np.asarray(start, dtype=np.float64), nan=0.0))
        s_prev, f_prev = s.copy(), np.zeros(len(d))
        brackets = []
        active = np.flatnonzero(down)
        radii = np.asarray(self.RADII, float) * self.cell
        with np.errstate(divide="ignore"):
            probe = np.where(tau > 0, self.cell / tau, np.inf)
        for _ in range(max_steps):
            if active.size == 0:
                break
            p = o + s[active, None] * v[active]
            r, c, fr, fc, inside = self._patch(p[:, 0], p[:, 1])
            z, gx, gy = self._bilinear_at(r, c, fr, fc, gradient=True)
            f = p[:, 2] - z
            below = inside & (f < 0)
            brackets.append((active[below], f[below]))
            arrived = inside & (f >= 0) & (f < tol)
            out[active[arrived]] = p[arrived]
            keep = inside & (f >= tol)
            active, r, c, f = active[keep], r[keep], c[keep], f[keep]
            t = tau[active]
            rise = 1.0 + gx[keep] * v[active, 0] + gy[keep] * v[active, 1]  # -d(f)/d(drop)
            newton = np.where(rise > 0.1, f / np.maximum(rise, 0.1), f)
            step = np.minimum(newton, probe[active])
            pz = p[keep, 2]
            with np.errstate(divide="ignore"):
                for radius, bound, top in zip(radii, self.bounds, self.tops):
                    reach = radius / t  # the drop that keeps the ray within `radius`
                    step = np.maximum(step, np.minimum(f / (1 + bound[r, c] * t), reach))
                    step = np.maximum(step, np.minimum(pz - top[r, c], reach))
            s_prev[active], f_prev[active] = s[active], f
            s[active] += step
        if active.size:
            log.debug("%d rays did not arrive in %d steps", active.size, max_steps)
        idx = np.concatenate([b[0] for b in brackets]) if brackets else np.zeros(0, np.intp)
        f_hi = np.concatenate([b[1] for b in brackets]) if brackets else np.zeros(0)
        out[idx] = self._false_position(o, v[idx], s_prev[idx], f_prev[idx], s[idx], f_hi, tol)
        return out

    def _false_position(self, o, v, lo, f_lo, hi, f_hi, tol, iterations: int = 30) -> np.ndarray:
        """Hits inside brackets ``f(lo) >= 0 > f(hi)`` of ``f``, the height above the surface
        along ``o + drop * v`` (Illinois variant of false position)."""
        side = np.zeros(len(lo), np.int8)
        for _ in range(iterations):
            if lo.size == 0:
                break
            mid = hi - f_hi * (hi - lo) / (f_hi - f_lo)
            mid = np.where(np.isfinite(mid) & (mid > lo) & (mid < hi), mid, 0.5 * (lo + hi))
            p = o + mid[:, None] * v
            r, c, fr, fc, _ = self._patch(p[:, 0], p[:, 1])
            f = p[:, 2] - self._bilinear_at(r, c, fr, fc)
            above = f >= 0
            lo, f_lo = np.where(above, mid, lo), np.where(above, f, f_lo)
            hi, f_hi = np.where(above, hi, mid), np.where(above, f_hi, f)
            # Illinois: halve the stale end's value when the same end moves twice
            f_hi = np.where(above & (side == 1), 0.5 * f_hi, f_hi)
            f_lo = np.where(~above & (side == -1), 0.5 * f_lo, f_lo)
            side = np.where(above, 1, -1).astype(np.int8)
            if np.all((f_lo < tol) | (hi - lo < 1e-6 * self.cell)):
                break
        p = o + lo[:, None] * v
        return np.column_stack([p[:, :2], self.height(p[:, 0], p[:, 1])])

    def _bilinear_at(self, r, c, fr, fc, *, gradient: bool = False):
        """Heights (and with ``gradient`` their x and y derivatives) at fractional positions
        ``fr, fc`` in the patches ``r, c``."""
        h = self.h
        a, b, e, g = h[r, c], h[r, c + 1], h[r + 1, c], h[r + 1, c + 1]
        top, bottom = a + (b - a) * fc, e + (g - e) * fc
        z = top + (bottom - top) * fr
        if not gradient:
            return z
        dz_dc = (b - a) * (1 - fr) + (g - e) * fr
        dz_dr = bottom - top
        return z, dz_dc / self.cell, -dz_dr / self.cell


def _bilinear(image: np.ndarray, rf: np.ndarray, cf: np.ndarray) -> np.ndarray:
    """Bilinear samples of a (rows, cols) or (rows, cols, bands) image at fractional
    row/column coordinates of cell centres (edges clamped)."""
    rows, cols = image.shape[:2]
    rf = np.clip(rf, 0, rows - 1)
    cf = np.clip(cf, 0, cols - 1)
    r = np.minimum(np.floor(rf).astype(np.intp), rows - 2)
    c = np.minimum(np.floor(cf).astype(np.intp), cols - 2)
    fr, fc = rf - r, cf - c
    if image.ndim == 3:
        fr, fc = fr[:, None], fc[:, None]
    return ((image[r, c] * (1 - fc) + image[r, c + 1] * fc) * (1 - fr)
            + (image[r + 1, c] * (1 - fc) + image[r + 1, c + 1] * fc) * fr)


@dataclass(frozen=True, eq=False)
class Texture:
    """What the ground looks like: a grey (rows, cols) or RGB (rows, cols, 3) image, values
    0..1, on a north-up grid of cell centres with upper-left corner ``(x0, y0)``."""

    image: np.ndarray = field(repr=False)
    x0: float
    y0: float
    cell: float

    def sample(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        return _bilinear(self.image, (self.y0 - y) / self.cell - 0.5,
                         (x - self.x0) / self.cell - 0.5)


def make_texture(ortho: np.ndarray, *, x0: float, y0: float, cell: float, gsd: float,
                 rng: np.random.Generator, detail: float = 0.05) -> Texture:
    """The orthoimage as seen at ``gsd``: blurred against aliasing where a pixel covers more
    than a cell; where a cell covers two pixels or more, resampled to a finer grid
    and given fine detail (a fixed random field on the ground, spectrum ~ 1/k, wavelengths
    from two fine cells up, standard deviation ``detail``), which the orthoimage lacks and
    which every image then sees in the same place."""
    from tiereg.simulate.world import _fractal

    image = np.asarray(ortho, dtype=np.float32)
    ratio = gsd / cell
    if ratio > 1.0:
        sigma = 0.5 * np.sqrt(ratio**2 - 1.0)
        return Texture(ndimage.gaussian_filter(image, (sigma, sigma, 0)[:image.ndim]),
                       x0, y0, cell)
    if ratio >= 0.5:
        return Texture(image, x0, y0, cell)
    k = max(2, int(np.floor(1.0 / ratio / 1.5)))
    rows, cols = image.shape[:2]
    fine = cell / k
    # fine cell centres in the coarse grid's fractional coordinates
    rf = (np.arange(rows * k) + 0.5) / k - 0.5
    cf = (np.arange(cols * k) + 0.5) / k - 0.5
    R, C = np.meshgrid(rf, cf, indexing="ij")
    up = _bilinear(image, R.ravel(), C.ravel()).reshape((rows * k, cols * k) + image.shape[2:])
    noise = detail * _fractal((rows * k, cols * k), fine, 1.0, rng, min_wavelength_m=2 * fine)
    if up.ndim == 3:
        noise = noise[:, :, None]
    return Texture(np.clip(up + noise, 0.0, 1.0).astype(np.float32), x0, y0, fine)


def cast_pixels(field_: HeightField, camera: Camera, pose: Pose, *,
                stride: int = 4) -> np.ndarray:
    """(rows, cols, 3) surface points seen at the pixel centres (NaN where a ray missed).

    The rays of every ``stride``-th pixel are cast first; each pixel's ray then starts a few
    cells above the nearest of the surrounding hits (rays between neighbouring rays meet the same
    surface unless something thinner than ``stride`` pixels pokes out between them)."""
    rows, cols = camera.height_px, camera.width_px
    vc = np.arange(0, rows + stride, stride, dtype=float)
    uc = np.arange(0, cols + stride, stride, dtype=float)
    V, U = np.meshgrid(vc, uc, indexing="ij")
    coarse = field_.intersect(pose.centre, pose.world_rays(camera, U.ravel(), V.ravel()))
    drop = (pose.centre[2] - coarse[:, 2]).reshape(V.shape)
    drop = np.where(np.isnan(drop), 0.0, drop)  # a miss: start from the top
    # the smallest drop of the 2 x 2 coarse rays around each pixel, less a margin
    lowest = np.minimum(np.minimum(drop[:-1, :-1], drop[1:, :-1]),
                        np.minimum(drop[:-1, 1:], drop[1:, 1:]))
    v, u = np.mgrid[0:rows, 0:cols]
    start = lowest[v // stride, u // stride] - field_.cell
    d = pose.world_rays(camera, u.ravel() + 0.5, v.ravel() + 0.5)
    # the start is a vertical drop; along the ray that is the same drop
    return field_.intersect(pose.centre, d, start=start.ravel()).reshape(rows, cols, 3)


def render_image(field_: HeightField, texture: Texture, camera: Camera, pose: Pose, *,
                 rng: np.random.Generator, noise_grey: float = 1.5,
                 gain: float = 1.0) -> tuple[np.ndarray, float]:
    """The 8-bit image (grey or RGB as the texture) and the share of pixels whose rays missed
    the surface (left black). A slight blur (0.5 pixel) and sensor noise are added."""
    hits = cast_pixels(field_, camera, pose).reshape(-1, 3)
    miss = np.isnan(hits[:, 0])
    grey = texture.sample(np.nan_to_num(hits[:, 0]), np.nan_to_num(hits[:, 1])) * gain * 255.0
    grey[miss] = 0.0
    bands = texture.image.shape[2:]
    img = ndimage.gaussian_filter(grey.reshape((camera.height_px, camera.width_px) + bands),
                                  (0.5, 0.5) + (0,) * len(bands))
    img = img + rng.normal(0.0, noise_grey, img.shape)
    return np.clip(np.rint(img), 0, 255).astype(np.uint8), float(miss.mean())
