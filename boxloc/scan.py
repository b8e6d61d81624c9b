"""The scan model: a range image, a sensor model that maps pixels to rays, and a noise model.

Frames and units
----------------
Everything is in the sensor frame, metres and radians: x right, y down, z forward.
A *range* is the distance along a pixel's unit ray, so the organized cloud is
``points = range[..., None] * rays``, an (H, W, 3) float32 array with NaN for no return.
"""

from __future__ import annotations

import dataclasses
import functools
import hashlib
from dataclasses import dataclass, field
from functools import cached_property
from typing import Any, overload

import numpy as np
import numpy.typing as npt

from boxloc.errors import InputError

FloatArray = npt.NDArray[np.floating[Any]]


def _readonly(a: np.ndarray) -> np.ndarray:
    """A private, read-only, C-contiguous copy: products never alias their inputs."""
    a = np.array(a, copy=True, order="C")
    a.flags.writeable = False
    return a


#: Largest image (pixels) whose pinhole rays are cached: 1920x1080, 50 MB per entry.
RAY_CACHE_PIXELS = 1920 * 1080


@functools.lru_cache(maxsize=2)
def _pinhole_rays(fx: float, fy: float, cx: float, cy: float, width: int,
                  height: int) -> np.ndarray:
    # each ray's length from its column's and row's terms, element-wise: the operations of
    # ``d / np.linalg.norm(d, axis=-1)`` over d = (x, y, 1), in their order (the same bits,
    # tests/test_scan.py), without the (H, W) grids and temporaries (27 -> 6 ms at 640x480)
    x = (np.arange(width, dtype=np.float64) - cx) / fx
    y = (np.arange(height, dtype=np.float64) - cy) / fy
    n = np.sqrt((x * x)[None, :] + (y * y)[:, None] + 1.0)
    d = np.empty((height, width, 3))
    np.divide(x[None, :], n, out=d[..., 0])
    np.divide(y[:, None], n, out=d[..., 1])
    np.divide(1.0, n, out=d[..., 2])
    d.flags.writeable = False
    return d


@dataclass(frozen=True)
class PinholeModel:
    """A pinhole camera: pixel (row v, column u) looks along ``((u-cx)/fx, (v-cy)/fy, 1)``.

    Parameters
    ----------
    fx, fy : float
        Focal lengths, pixels.
    cx, cy : float
        Principal point, pixels (column, row).
    width, height : int
        Image size, pixels.
    """

    fx: float
    fy: float
    cx: float
    cy: float
    width: int
    height: int

    def __post_init__(self) -> None:
        vals = (self.fx, self.fy, self.cx, self.cy)
        if not all(np.isfinite(v) for v in vals):
            raise InputError(f"intrinsics must be finite, got fx,fy,cx,cy = {vals}")
        if self.fx <= 0 or self.fy <= 0:
            raise InputError(f"focal lengths must be positive, got fx={self.fx}, fy={self.fy}")
        if self.width <= 0 or self.height <= 0:
            raise InputError(f"image size must be positive, got {self.width}x{self.height}")

    kind = "pinhole"

    @property
    def shape(self) -> tuple[int, int]:
        return (self.height, self.width)

    @property
    def K(self) -> np.ndarray:
        """The 3x3 intrinsic matrix."""
        return np.array(
            [[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]], dtype=np.float64
        )

    @classmethod
    def from_K(cls, K: npt.ArrayLike, width: int, height: int) -> PinholeModel:
        K = np.asarray(K, dtype=np.float64)
        if K.shape != (3, 3):
            raise InputError(f"intrinsics must have shape (3, 3), got {K.shape}")
        return cls(float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]), width, height)

    def rays(self) -> np.ndarray:
        """Unit rays, shape (H, W, 3), float64, read-only.

        Cached per model up to :data:`RAY_CACHE_PIXELS`: a stream of scans from one camera
        builds them once (6 ms at 640x480, 17 ms at 1280x960, otherwise paid on every
        scan). Larger images build them each time, so that a huge scan's rays (400 MB
        at 4096x4096) do not stay alive beside its pipeline.
        """
        args = (self.fx, self.fy, self.cx, self.cy, self.width, self.height)
        if self.width * self.height > RAY_CACHE_PIXELS:
            return _pinhole_rays.__wrapped__(*args)
        return _pinhole_rays(*args)

    def project(self, P_sensor: FloatArray) -> np.ndarray:
        """Project points (..., 3) to pixel coordinates (..., 2) as (column u, row v), float64.

        Points with z <= 0 project to NaN.
        """
        P = np.asarray(P_sensor, dtype=np.float64)
        z = P[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            u = self.fx * P[..., 0] / z + self.cx
            v = self.fy * P[..., 1] / z + self.cy
        uv = np.stack([u, v], -1)
        uv[z <= 0] = np.nan
        return uv

    @property
    def pixel_angle(self) -> float:
        """Angular size of one pixel at the principal point, radians."""
        return float(1.0 / np.sqrt(self.fx * self.fy))

    def to_dict(self) -> dict[str, Any]:
        return {"kind": "pinhole", "fx": self.fx, "fy": self.fy, "cx": self.cx, "cy": self.cy,
                "width": self.width, "height": self.height}


@dataclass(frozen=True, eq=False)
class RayTableModel:
    """An explicit unit ray per pixel, for scanners that are not pinhole (e.g. a laser on a hand).

    Parameters
    ----------
    table : ndarray, shape (H, W, 3), float64
        Unit ray of each pixel in the sensor frame. NaN where a pixel has no ray.
    """

    table: np.ndarray

    kind = "raytable"

    def __post_init__(self) -> None:
        t = np.asarray(self.table)
        if not (np.issubdtype(t.dtype, np.floating) or np.issubdtype(t.dtype, np.integer)):
            raise InputError(f"ray table must be a real number array, got dtype {t.dtype}")
        t = t.astype(np.float64)
        if t.ndim != 3 or t.shape[2] != 3:
            raise InputError(f"ray table must have shape (H, W, 3), got {t.shape}")
        if np.isinf(t).any():
            raise InputError("ray table must be finite or NaN")
        n = np.linalg.norm(t, axis=-1, keepdims=True)
        # normalize only rays that are not unit already, so a table survives a round trip
        # through this constructor bit for bit
        with np.errstate(invalid="ignore", divide="ignore"):
            t = np.where(np.abs(n - 1.0) <= 1e-12, t, np.where(n > 0, t / n, np.nan))
        object.__setattr__(self, "table", _readonly(t))

    @property
    def shape(self) -> tuple[int, int]:
        return (int(self.table.shape[0]), int(self.table.shape[1]))

    @property
    def width(self) -> int:
        return self.shape[1]

    @property
    def height(self) -> int:
        return self.shape[0]

    def rays(self) -> np.ndarray:
        return self.table

    @cached_property
    def _tree(self) -> tuple[Any, np.ndarray]:
        from scipy.spatial import cKDTree

        flat = self.table.reshape(-1, 3)
        ok = np.flatnonzero(np.isfinite(flat).all(1))
        return cKDTree(flat[ok]), ok

    def project(self, P_sensor: FloatArray) -> np.ndarray:
        """Pixel (u, v) of the ray nearest each point's direction; NaN if none is near."""
        P = np.asarray(P_sensor, dtype=np.float64)
        shp = P.shape[:-1]
        d = P.reshape(-1, 3)
        n = np.linalg.norm(d, axis=1, keepdims=True)
        with np.errstate(invalid="ignore", divide="ignore"):
            d = d / n
        tree, ok = self._tree
        good = np.isfinite(d).all(1)
        uv = np.full((d.shape[0], 2), np.nan)
        if good.any():
            dist, idx = tree.query(d[good])
            flat = ok[idx]
            r, c = np.divmod(flat, self.width)
            near = dist < 3 * self.pixel_angle
            out = np.stack([c, r], -1).astype(np.float64)
            out[~near] = np.nan
            uv[good] = out
        return uv.reshape(*shp, 2)

    @cached_property
    def pixel_angle(self) -> float:
        t = self.table
        dots = np.einsum("ijk,ijk->ij", t[:, 1:], t[:, :-1])
        dots = dots[np.isfinite(dots)]
        if dots.size == 0:
            return 1e-3
        return float(np.median(np.arccos(np.clip(dots, -1, 1))))

    def to_dict(self) -> dict[str, Any]:
        return {"kind": "raytable", "width": self.width, "height": self.height}


SensorModel = PinholeModel | RayTableModel


@dataclass(frozen=True)
class NoiseModel:
    """Standard deviation of a range measurement as a function of range and incidence.

    ``sigma_range(r, cos_i) = sqrt(sigma0**2 + (k1*r)**2 + (k2*r**2)**2) / max(cos_i, min_cos)**g``

    with ``g`` the ``incidence_exponent``.

    The quadratic term models triangulation sensors (Kinect-style depth quantization
    grows with range squared); the constant term models time-of-flight scanners.
    Lateral noise is ``r * sqrt(sigma_angle**2 + pixel_angle**2 / 12)``.

    Parameters
    ----------
    sigma0 : float
        Constant range noise, metres.
    k1 : float
        Range noise growing linearly with range, metres per metre.
    k2 : float
        Range noise growing with range squared, 1/metres.
    sigma_angle : float
        Beam pointing jitter, radians.
    min_cos : float
        Floor on the cosine of the incidence angle, so grazing points stay finite.
    edge_px : float
        Standard deviation of an edge's position along the scan line that crosses it, beyond
        the pixel grid's own quantization, pixels. Structured-light sensors blur and shift
        depth edges by about a pixel (their correlation window); an ideal scanner has 0.
        On a surface seen at grazing incidence one pixel is several millimetres.
    row_corr : float
        Correlation of the range noise of two points in the same image row, in [0, 1):
        the share of the noise variance that is an offset common to the whole row.
        Structured-light sensors have one (the mOSD Kinect frames: 0.28); it does not
        average out along a row, so tests that average points along a line (seams) need
        it. An ideal scanner has 0.
    incidence_exponent : float
        How the range noise grows as the surface turns from the ray: by ``1 / cos**g``.
        1 is a triangulation sensor whose footprint stretches along the ray; a laser or
        time-of-flight sensor's range noise hardly depends on the incidence (g near 0).
    corr_px_rows, corr_px_cols : float
        Correlation length of the range noise along image rows and along columns, pixels:
        two samples k pixels apart correlate by exp(-k / length). Stereo and
        structured-light sensors match windows of several pixels, so neighbouring samples
        share their error and a line fitted to a few of them wobbles as a whole (the edge
        stage's crease test takes it into account). 0: white noise, as a scanner's.
    exceed_rate : float
        Share of a flat surface's points beyond the point test's critical value (z at
        alpha / 2) on one side, as the scan's flat tiles show it (the median tile's, half
        of both sides). 0: the normal's alpha / 2. Active-stereo depth has heavy tails: 1-3 %
        of its points lie beyond 2.58 sigma on a side, not 0.5 %.
    exceed_dispersion : float
        How much more the count of such points varies from one 16x16 px tile to the next
        than independent points' would (a robust variance ratio, at least 1): where the
        noise's amplitude varies smoothly over the image, its exceedances come in patches.
        1: as the correlation terms above say. The exposure test divides its counts by it.
    exceed_corr_px : float
        How far those counts correlate from tile to tile: ``exp(-d / exceed_corr_px)`` for
        tiles d pixels apart (centre to centre), from the correlation of neighbouring flat
        tiles' counts where it is significant at alpha. A face's core spans many tiles,
        and where the patches are larger than a tile its count varies more than
        ``exceed_dispersion`` says: the exposure test widens it by the core's tiles' design
        effect. 0: the tiles' counts are independent.
    """

    sigma0: float = 0.0010
    k1: float = 0.0
    k2: float = 0.0006
    sigma_angle: float = 0.0003
    min_cos: float = 0.2
    edge_px: float = 0.0
    row_corr: float = 0.0
    incidence_exponent: float = 1.0
    corr_px_rows: float = 0.0
    corr_px_cols: float = 0.0
    exceed_rate: float = 0.0
    exceed_dispersion: float = 1.0
    exceed_corr_px: float = 0.0

    def __post_init__(self) -> None:
        for name in ("sigma0", "k1", "k2", "sigma_angle", "min_cos", "edge_px",
                     "corr_px_rows", "corr_px_cols"):
            v = getattr(self, name)
            if not np.isfinite(v) or v < 0:
                raise InputError(f"noise parameter {name} must be finite and >= 0, got {v}")
        if self.sigma0 == 0 and self.k1 == 0 and self.k2 == 0:
            raise InputError("noise model needs sigma0, k1 or k2 > 0")
        if not (np.isfinite(self.row_corr) and 0 <= self.row_corr < 1):
            raise InputError(f"noise parameter row_corr must be in [0, 1), got {self.row_corr}")
        if not (np.isfinite(self.incidence_exponent) and 0 <= self.incidence_exponent <= 3):
            raise InputError("noise parameter incidence_exponent must be in [0, 3], got "
                             f"{self.incidence_exponent}")
        if not (np.isfinite(self.exceed_rate) and 0 <= self.exceed_rate < 0.5):
            raise InputError(f"noise parameter exceed_rate must be in [0, 0.5), got "
                             f"{self.exceed_rate}")
        if not (np.isfinite(self.exceed_dispersion) and self.exceed_dispersion >= 1):
            raise InputError(f"noise parameter exceed_dispersion must be finite and >= 1, "
                             f"got {self.exceed_dispersion}")
        if not (np.isfinite(self.exceed_corr_px) and self.exceed_corr_px >= 0):
            raise InputError(f"noise parameter exceed_corr_px must be finite and >= 0, got "
                             f"{self.exceed_corr_px}")
        if not 0 < self.min_cos <= 1:
            raise InputError(f"noise parameter min_cos must be in (0, 1], got {self.min_cos}")

    @property
    def correlated(self) -> bool:
        """Whether the noise is spatially correlated: a correlation length along rows or
        columns (the seam tests then measure their statistic's spread)."""
        return self.corr_px_rows > 0 or self.corr_px_cols > 0

    @overload
    def sigma_range(self, r: float, cos_incidence: float = 1.0) -> float: ...

    @overload
    def sigma_range(self, r: FloatArray,
                    cos_incidence: FloatArray | float = 1.0) -> np.ndarray: ...

    def sigma_range(self, r: FloatArray | float,
                    cos_incidence: FloatArray | float = 1.0) -> np.ndarray | float:
        """Range standard deviation, metres, same shape as ``r`` (a float for a float)."""
        r = np.asarray(r, dtype=np.float64)
        s = np.sqrt(self.sigma0**2 + (self.k1 * r) ** 2 + (self.k2 * r * r) ** 2)
        c = np.maximum(np.abs(np.asarray(cos_incidence, dtype=np.float64)), self.min_cos)
        return s / c**self.incidence_exponent

    def sigma_lateral(self, r: FloatArray, pixel_angle: float) -> np.ndarray:
        """Lateral standard deviation perpendicular to the ray, metres."""
        r = np.asarray(r, dtype=np.float64)
        return r * np.sqrt(self.sigma_angle**2 + pixel_angle**2 / 12.0)

    def covariance(
        self, P_sensor: FloatArray, pixel_angle: float, cos_incidence: FloatArray | float = 1.0
    ) -> np.ndarray:
        """Covariance of points (N, 3) in the sensor frame, shape (N, 3, 3), metres squared."""
        P = np.asarray(P_sensor, dtype=np.float64).reshape(-1, 3)
        r = np.linalg.norm(P, axis=1)
        d = P / np.maximum(r, 1e-12)[:, None]
        sr = self.sigma_range(r, cos_incidence)
        sl = self.sigma_lateral(r, pixel_angle)
        ddT = d[:, :, None] * d[:, None, :]
        eye = np.eye(3)[None]
        return (sr**2)[:, None, None] * ddT + (sl**2)[:, None, None] * (eye - ddT)

    def pixel_footprint(self, P_sensor: FloatArray, directions: FloatArray,
                        pixel_angle: float) -> np.ndarray:
        """Length on the surface of one pixel step along unit ``directions`` (N, 3) at points
        (N, 3), metres, shape (N,): the pixel's angle at the point's range, foreshortened by
        the angle between the direction and the ray (floored at ``min_cos``)."""
        P = np.asarray(P_sensor, dtype=np.float64).reshape(-1, 3)
        d = np.asarray(directions, dtype=np.float64).reshape(-1, 3)
        r = np.linalg.norm(P, axis=1)
        cos = np.einsum("ij,ij->i", d, P) / np.maximum(r, 1e-12)
        sin = np.sqrt(np.clip(1.0 - cos**2, 0.0, 1.0))
        return r * pixel_angle / np.maximum(sin, self.min_cos)

    def to_dict(self) -> dict[str, float]:
        """Every parameter, defaults included."""
        return dataclasses.asdict(self)


def _check_range(range_: npt.ArrayLike) -> np.ndarray:
    a = np.asarray(range_)
    if a.ndim != 2:
        raise InputError(f"range must have shape (H, W), got {a.shape}")
    if a.size == 0:
        raise InputError(f"range must not be empty, got shape {a.shape}")
    if not np.issubdtype(a.dtype, np.floating):
        raise InputError(f"range must be a float array, got dtype {a.dtype}")
    with np.errstate(over="ignore"):  # an overflow becomes inf, refused just below
        a = a.astype(np.float32, copy=False)
    if np.isinf(a).any():
        raise InputError("range must be finite or NaN, found inf")
    if (a < 0).any():
        raise InputError("range must be >= 0 (NaN for no return), found negative values")
    # A zero range is a sensor's "no return"; NaN is ours.
    a = np.where(a == 0, np.float32(np.nan), a)
    return a


@dataclass(frozen=True, eq=False)
class Scan:
    """One range scan.

    Parameters
    ----------
    range : ndarray, shape (H, W), float32
        Metres along each pixel's ray; NaN for no return.
    sensor : PinholeModel or RayTableModel
        Maps pixels to rays; its shape must equal ``range.shape``.
    capture_time_ns : int
        Capture time, integer nanoseconds since the epoch (0 when unknown).
    index : int
        Sequence number of the scan in its source (0-based).
    sensor_to_base : ndarray, shape (4, 4), optional
        Pose of the sensor in the robot base frame, when known.
    source : str
        Where the scan came from (a path, a simulator spec); informational.
    """

    range: np.ndarray
    sensor: SensorModel
    capture_time_ns: int = 0
    index: int = 0
    sensor_to_base: np.ndarray | None = None
    source: str = ""
    meta: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if not isinstance(self.sensor, PinholeModel | RayTableModel):
            raise TypeError(
                f"sensor must be a PinholeModel or RayTableModel, got {type(self.sensor)}"
            )
        r = _check_range(self.range)
        if r.shape != self.sensor.shape:
            raise InputError(
                f"range shape {r.shape} does not match the sensor model's {self.sensor.shape}"
            )
        if isinstance(self.sensor, RayTableModel):
            # A pixel without a ray cannot have a return (its point would be NaN while the
            # range says valid, and the stages would fit planes through NaN).
            noray = ~np.isfinite(self.sensor.table).all(-1)
            if noray.any():
                r = np.where(noray, np.float32(np.nan), r)
        object.__setattr__(self, "range", _readonly(r))
        if self.sensor_to_base is not None:
            T = np.asarray(self.sensor_to_base, dtype=np.float64)
            if T.shape != (4, 4) or not np.isfinite(T).all():
                raise InputError(f"sensor_to_base must be a finite (4, 4) matrix, got {T.shape}")
            object.__setattr__(self, "sensor_to_base", _readonly(T))
        t, i = int(self.capture_time_ns), int(self.index)
        # Both are stored as int64 (npz, logs): refuse what would not fit, here, clearly.
        if not 0 <= t < 2**63:
            raise InputError(f"capture_time_ns must be in [0, 2**63) nanoseconds, got {t}")
        if not -(2**63) <= i < 2**63:
            raise InputError(f"scan index must fit in 64 bits, got {i}")
        object.__setattr__(self, "capture_time_ns", t)
        object.__setattr__(self, "index", i)

    @property
    def shape(self) -> tuple[int, int]:
        return (int(self.range.shape[0]), int(self.range.shape[1]))

    @cached_property
    def points(self) -> np.ndarray:
        """Organized cloud, shape (H, W, 3), float32, metres, NaN for no return."""
        with np.errstate(invalid="ignore"):
            p = (self.range[..., None].astype(np.float64) * self.sensor.rays()).astype(np.float32)
        p[~np.isfinite(self.range)] = np.nan
        p.flags.writeable = False
        return p

    @property
    def valid(self) -> np.ndarray:
        """Mask of pixels with a return, shape (H, W), bool."""
        return np.isfinite(self.range)

    @cached_property
    def seed(self) -> int:
        """A 63-bit seed derived from the scan content, for reproducible random trials."""
        h = hashlib.blake2b(digest_size=8)
        h.update(np.asarray(self.range.shape, dtype=np.int64).tobytes())
        h.update(np.ascontiguousarray(self.range).tobytes())
        return int.from_bytes(h.digest(), "little") >> 1

    @property
    def up(self) -> np.ndarray:
        """The world's up direction in the sensor frame (unit, (3,)).

        From the base pose when known (base z is up); else toward the sensor, ``-z``.
        """
        if self.sensor_to_base is not None:
            up = self.sensor_to_base[:3, :3].T @ np.array([0.0, 0.0, 1.0])
            return up / np.linalg.norm(up)
        return np.array([0.0, 0.0, -1.0])

    @classmethod
    def from_points(
        cls,
        points: npt.ArrayLike,
        intrinsics: npt.ArrayLike | None = None,
        **kwargs: Any,
    ) -> Scan:
        """Build a scan from an organized cloud (H, W, 3), metres, sensor frame, NaN = no return.

        With ``intrinsics`` (3x3) the sensor is pinhole. Without, a pinhole model is fitted
        to the points; if it does not fit to 0.05 px, the rays are kept as a ray table.
        """
        P = np.asarray(points)
        if P.ndim != 3 or P.shape[2] != 3:
            raise InputError(f"points must have shape (H, W, 3), got {P.shape}")
        if P.shape[0] == 0 or P.shape[1] == 0:
            raise InputError(f"points must not be empty, got shape {P.shape}")
        if not np.issubdtype(P.dtype, np.floating):
            raise InputError(f"points must be a float array, got dtype {P.dtype}")
        P = P.astype(np.float64)
        if np.isinf(P).any():
            raise InputError("points must be finite or NaN, found inf")
        bad = ~np.isfinite(P).all(-1)
        P[bad] = np.nan
        r = np.linalg.norm(P, axis=-1)
        r[r == 0] = np.nan
        H, W = P.shape[:2]
        sensor: SensorModel
        if intrinsics is not None:
            sensor = PinholeModel.from_K(intrinsics, W, H)
        else:
            sensor = _fit_pinhole(P, W, H) or RayTableModel(P / r[..., None])
        with np.errstate(over="ignore"):  # beyond float32: inf, which the range check refuses
            r32 = r.astype(np.float32)
        return cls(range=r32, sensor=sensor, **kwargs)


def _fit_pinhole(P: np.ndarray, W: int, H: int) -> PinholeModel | None:
    """Least-squares pinhole fit of an organized cloud; None if it does not fit to 0.05 px."""
    ok = np.isfinite(P).all(-1) & (P[..., 2] > 0)
    if ok.sum() < 10:
        return None
    v, u = np.nonzero(ok)
    X = P[ok]
    a = X[:, 0] / X[:, 2]
    b = X[:, 1] / X[:, 2]
    if np.ptp(a) == 0 or np.ptp(b) == 0:
        return None
    fx, cx = np.polyfit(a, u, 1)
    fy, cy = np.polyfit(b, v, 1)
    res = max(np.abs(fx * a + cx - u).max(), np.abs(fy * b + cy - v).max())
    if res > 0.05 or fx <= 0 or fy <= 0:
        return None
    return PinholeModel(float(fx), float(fy), float(cx), float(cy), W, H)


def sensor_from_dict(d: dict[str, Any], table: np.ndarray | None = None) -> SensorModel:
    """Inverse of ``sensor.to_dict()``; a ray table needs its ``table`` array."""
    if d.get("kind") == "pinhole":
        return PinholeModel(float(d["fx"]), float(d["fy"]), float(d["cx"]), float(d["cy"]),
                            int(d["width"]), int(d["height"]))
    if d.get("kind") == "raytable":
        if table is None:
            raise InputError("a ray-table sensor model needs its table")
        return RayTableModel(table)
    raise InputError(f"unknown sensor model kind {d.get('kind')!r}")
