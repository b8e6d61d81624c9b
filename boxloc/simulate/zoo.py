"""A zoo of range-sensor models for the simulator, built from physics and measured figures.

The simulator's default sensor draws its range noise from :class:`boxloc.scan.NoiseModel`,
the model the localizer itself assumes. The sensors here do not: each is a documented
physical model whose parameters come from datasheets, the literature and the figures
measured on real frames (issue 20, "Real active-stereo depth, measured"). None of them
imports or evaluates ``NoiseModel``.

Sensors (:data:`SENSORS`)
-------------------------
``laser``
    A pulsed time-of-flight laser range finder, the paper's sensor class (Katsoulas used a
    laser range finder on the robot's hand; SICK LMS-200 class). White Gaussian range
    noise: a constant timing term plus a shot-noise term that grows with r^2 / (rho cos i)
    (negligible below ~5 m on cardboard). Mixed pixels from beam divergence: the footprint
    (:data:`LASER_DIVERGENCE` rad) straddling a jump returns the power-weighted mean of the
    ranges it covers when the echoes overlap in time, else the strongest echo.
``structured-light``
    A Kinect-v1-class projector and IR camera. Depth from disparity z = f b / d with
    b = :data:`SL_BASELINE`; disparity noise :data:`SL_SIGMA_D` px (so sigma_z grows as z^2);
    disparity reported in 1/8 px steps (depth steps of z^2 / (8 f b)); a share
    :data:`SL_ROW_SHARE` of the disparity-noise variance common to an image row; the
    correlation window fattens foreground edges by up to a pixel; projector shadows beside
    jumps; no return at grazing incidence and on shiny tape.
``active-stereo``
    A projected-pattern stereo camera (OAK-D-Pro or RealSense class, :data:`STEREO_CLASSES`).
    sigma by depth as measured; spatially correlated noise that reproduces the measured
    residual correlations; heavy tails from a slowly varying matching quality; edges rounded
    by a disparity-domain blur of 2-6 px (10-90 %); holes at depth jumps, in the occlusion
    band of the second camera, on dark patches and on shiny tape.
``tof``
    An AMCW time-of-flight camera (Kinect v2 / Azure Kinect class). Shot-noise-limited range
    noise sigma ~ r / sqrt(rho cos i); flying pixels at jumps from the phasor sum over the
    pixel's footprint; multipath at concave (inside) corners: ranges too long, decaying away
    from the corner; no return where the returned amplitude is too low.

Each sensor's noise scale is drawn over :data:`NOISE_SCALE_RANGE` (log-uniform) times its
nominal from the scene seed, unless the scene gives it.

Units: metres, radians, pixels. Arrays over the image are flat, (N,) = (H * W,), row-major.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
from scipy.ndimage import binary_dilation, distance_transform_edt, gaussian_filter1d

__all__ = [
    "SENSORS",
    "STEREO_CLASSES",
    "NOISE_SCALE_RANGE",
    "Rendered",
    "draw_sensor",
    "measure",
    "laser_sigma",
    "tof_sigma",
    "structured_light_sigma",
    "active_stereo_sigma",
    "SL_BASELINE",
    "SL_SIGMA_D",
    "SL_STEP",
    "SL_ROW_SHARE",
    "STEREO_ROW_SHARE",
    "STEREO_TAIL",
]

SENSORS = ("laser", "tof", "structured-light", "active-stereo")
#: Active-stereo classes measured (issue 20): raw OAK-D-Pro depth, RealSense with post-filters.
STEREO_CLASSES = ("oak-d-pro", "realsense")
#: Range of the per-scene noise scale (times the nominal), drawn log-uniformly.
NOISE_SCALE_RANGE = (0.5, 3.0)

# --- laser (SICK LMS-200 class: statistical error ~5 mm 1-sigma up to 8 m on 10 % remission) ---
#: Timing (range-independent) noise, metres.
LASER_SIGMA0 = 0.0025
#: Shot-noise term at the reference range and remission, metres; grows as r^2 / (rho cos i).
LASER_SIGMA_SHOT = 0.004
LASER_R_REF, LASER_RHO_REF = 8.0, 0.10
#: Beam divergence (full angle), rad: the footprint is r * divergence wide.
LASER_DIVERGENCE = 0.0044
#: Echoes closer than half the pulse length (3 ns pulse) merge into one mixed return, m.
LASER_MERGE = 0.45

# --- time of flight (Kinect v2 / Azure Kinect class) ---
#: Read-out noise floor, metres.
TOF_SIGMA0 = 0.0005
#: Shot noise at 1 m on a rho = 0.5 surface at normal incidence, metres; ~ r / sqrt(rho cos i).
TOF_SIGMA1 = 0.0012
TOF_RHO_REF = 0.5
#: Modulation frequency, Hz (phase wraps at c / 2f = 1.87 m; mixing is a phasor sum).
TOF_FMOD = 80e6
#: Multipath at an inside corner: bias at the corner, metres, and its decay length, metres.
TOF_MULTIPATH = 0.012
TOF_MULTIPATH_LEN = 0.05
#: No return below this returned amplitude rho cos i / r^2 (1/m^2).
TOF_MIN_AMPLITUDE = 0.002

# --- structured light (Kinect v1: Khoshelham & Oude Elberink 2012; Smisek et al. 2011) ---
SL_BASELINE = 0.075
#: Disparity noise, pixels (1-sigma).
SL_SIGMA_D = 0.1
#: Disparity quantization step, pixels (the Kinect reports 1/8-pixel sub-pixel disparity).
SL_STEP = 1.0 / 8.0
#: Share of the disparity-noise variance common to an image row (mOSD Kinect frames: 0.28).
SL_ROW_SHARE = 0.3
SL_RANGE = (0.4, 8.0)

# --- active stereo (issue 20's measured figures) ---
#: sigma_z = c z^p: OAK-D-Pro raw depth 0.5 mm at 0.7 m ... 3.8 mm at 1.4 m (c = 1.4 mm/m^3);
#: RealSense with post-filters 1.3-1.7 mm at 2.2-2.5 m (c = 0.27 mm/m^2).
STEREO_LAW = {"oak-d-pro": (0.0014, 3.0), "realsense": (0.00027, 2.0)}
#: Stereo baselines, metres (OAK-D-Pro 7.5 cm; RealSense D435 5 cm).
STEREO_BASELINE = {"oak-d-pro": 0.075, "realsense": 0.05}
#: Variance shares of the correlated field: a row offset, a matching-window blob (Gaussian
#: smoothing sigma along rows, along columns, px), column streaks (exponential along columns),
#: white. Fitted to the measured residual correlations in 16 px tiles (see the tests).
STEREO_ROW_SHARE = 0.08
STEREO_BLOB = (0.57, 4.5, 1.7)
STEREO_STREAK = (0.30, 1.1, 80.0)
STEREO_WHITE = 0.05
#: Heavy tails: the noise is scaled by exp(a S), S a smooth unit Gaussian field. a = 0.6 puts
#: 5.7 % beyond 3 robust sigmas and 1.3 % beyond 5 (measured: 3.5-8 % and 0.6-3 %).
STEREO_TAIL = 0.6
STEREO_TAIL_LEN = 12.0
#: The measured sigmas are of residuals of 16 px tile plane fits, which absorb the field's
#: long-wavelength part (0.8-0.87 of its robust sigma remains): the field is scaled up so
#: that the tile residuals, not the raw field, have the measured sigma.
STEREO_TILE_GAIN = 1.2
#: Edge rounding: disparity blur sigma, px (10-90 % width 2.56 sigma = 2-6 px).
STEREO_EDGE_BLUR = (0.8, 2.3)
STEREO_RANGE = (0.3, 10.0)


@dataclass(frozen=True)
class Rendered:
    """The noise-free render a sensor model measures.

    Attributes
    ----------
    shape : (H, W)
    f : float
        Focal length, pixels.
    rays : (N, 3) float64
        Unit rays, sensor frame.
    r0 : (N,) float64
        Range along each ray, metres; NaN for no hit.
    cos_i : (N,) float64
        |cos| of the incidence angle; NaN for no hit.
    reflectivity : (N,) float64
        Diffuse reflectivity (albedo) of the surface hit, 0..1.
    shiny : (N,) bool
        A specular surface (packing tape).
    at_jump : (N,) bool
        Both pixels of every depth discontinuity of the render.
    concave : (N,) bool
        Pixels on an inside corner (a concave crease).
    shadow : callable
        ``shadow(baseline)``: (N,) bool, the points an emitter (or second camera)
        ``baseline`` metres along sensor x cannot see.
    footprint : callable
        ``footprint(pix, offsets)``: for pixels ``pix`` (M,) and sub-pixel offsets (S, 2)
        (du, dv in pixels), the range (M, S) (NaN for none), |cos i| (M, S) and reflectivity
        (M, S) of sub-rays.
    """

    shape: tuple[int, int]
    f: float
    rays: np.ndarray
    r0: np.ndarray
    cos_i: np.ndarray
    reflectivity: np.ndarray
    shiny: np.ndarray
    at_jump: np.ndarray
    concave: np.ndarray
    shadow: Callable[[float], np.ndarray]
    footprint: Callable[[np.ndarray, np.ndarray],
                        tuple[np.ndarray, np.ndarray, np.ndarray]]


# --- nominal noise laws --------------------------------------------------------------------------


def laser_sigma(r: np.ndarray | float, cos_i: np.ndarray | float = 1.0,
                rho: np.ndarray | float = 0.45) -> np.ndarray:
    """Laser range noise, metres: sqrt(sigma0^2 + (shot (r/r_ref)^2 (rho_ref/(rho cos)))^2)."""
    r = np.asarray(r, dtype=np.float64)
    c = np.maximum(np.asarray(cos_i, dtype=np.float64), 0.05)
    shot = LASER_SIGMA_SHOT * (r / LASER_R_REF) ** 2 * LASER_RHO_REF / (np.asarray(rho) * c)
    return np.sqrt(LASER_SIGMA0**2 + shot**2)


def tof_sigma(r: np.ndarray | float, cos_i: np.ndarray | float = 1.0,
              rho: np.ndarray | float = TOF_RHO_REF) -> np.ndarray:
    """ToF range noise, metres: sqrt(sigma0^2 + (sigma1 r sqrt(rho_ref / (rho cos)))^2)."""
    r = np.asarray(r, dtype=np.float64)
    c = np.maximum(np.asarray(cos_i, dtype=np.float64), 0.05)
    shot = TOF_SIGMA1 * r * np.sqrt(TOF_RHO_REF / (np.asarray(rho) * c))
    return np.sqrt(TOF_SIGMA0**2 + shot**2)


def structured_light_sigma(z: np.ndarray | float, f: float) -> np.ndarray:
    """Kinect depth noise, metres: z^2 / (f b) * sqrt(sigma_d^2 + step^2 / 12) (quantization
    dithered by the noise)."""
    z = np.asarray(z, dtype=np.float64)
    return z * z / (f * SL_BASELINE) * math.sqrt(SL_SIGMA_D**2 + SL_STEP**2 / 12)


def active_stereo_sigma(z: np.ndarray | float, cls: str) -> np.ndarray:
    """Active-stereo depth noise (robust sigma), metres: c z^p for the class."""
    c, p = STEREO_LAW[cls]
    return c * np.asarray(z, dtype=np.float64) ** p


# --- draws ---------------------------------------------------------------------------------------


def draw_sensor(sensor: str, rng: np.random.Generator) -> tuple[float, str | None]:
    """The scene's noise scale (log-uniform over NOISE_SCALE_RANGE) and sensor class.

    Both are drawn always (in this order), so giving one does not shift the other.
    """
    lo, hi = NOISE_SCALE_RANGE
    scale = round(float(math.exp(rng.uniform(math.log(lo), math.log(hi)))), 4)
    cls = STEREO_CLASSES[int(rng.integers(len(STEREO_CLASSES)))]
    return scale, (cls if sensor == "active-stereo" else None)


# --- shared pieces -------------------------------------------------------------------------------


def _unit_field(z: np.ndarray) -> np.ndarray:
    s = float(z.std())
    return z / s if s > 0 else z


def _ar_filter(z: np.ndarray, length: float, axis: int) -> np.ndarray:
    """Unit-variance AR(1) filter (exponential correlation exp(-lag / length)) along an axis."""
    # imported here: scipy.signal takes 0.4 s to import, which every process that imports
    # the simulator (the forkserver of `run --workers`, `boxloc simulate`) would pay otherwise
    from scipy.signal import lfilter

    a = math.exp(-1.0 / length)
    return lfilter([math.sqrt(1 - a * a)], [1.0, -a], z, axis=axis)


def _smooth(z: np.ndarray, sigma: float, axis: int) -> np.ndarray:
    return gaussian_filter1d(z, sigma, axis=axis, mode="reflect") if sigma > 0.05 else z


def _pixel_size(r: np.ndarray, f: float) -> np.ndarray:
    """Metres per pixel at range r (on a surface facing the sensor)."""
    return r / f


def _depth_of(ren: Rendered) -> np.ndarray:
    return ren.r0 * ren.rays[:, 2]


def _grid_offsets(half: float, n: int = 3) -> np.ndarray:
    g = np.linspace(-half, half, n)
    uu, vv = np.meshgrid(g, g)
    return np.stack([uu.ravel(), vv.ravel()], 1)


def _near_jump(ren: Rendered, px: int) -> np.ndarray:
    H, W = ren.shape
    m = ren.at_jump.reshape(H, W)
    if px > 0:
        m = binary_dilation(m, iterations=px)
    return m.ravel()


# --- the sensors ---------------------------------------------------------------------------------


def _laser(ren: Rendered, scale: float, rng: np.random.Generator) -> np.ndarray:
    N = ren.r0.size
    z = rng.standard_normal(N)
    u_drop = rng.random(N)
    r = ren.r0.copy()
    hit = np.isfinite(r)
    # Mixed pixels: the beam footprint (divergence * r, at least the pixel) straddles a jump.
    half = max(0.5, LASER_DIVERGENCE * ren.f / 2)
    pix = np.flatnonzero(_near_jump(ren, int(math.ceil(half))))
    if pix.size:
        off = _grid_offsets(half)
        prof = np.exp(-2 * (off**2).sum(1) / max(half, 1e-9) ** 2)  # Gaussian beam, 1/e^2 edge
        t, c, rho = ren.footprint(pix, off)
        with np.errstate(invalid="ignore", divide="ignore"):
            pw = np.where(np.isfinite(t), prof * rho * c / t**2, 0.0)
            tt = np.where(np.isfinite(t), t, 0.0)
            tot = pw.sum(1)
            mean = (pw * tt).sum(1) / tot
            strongest = tt[np.arange(pix.size), pw.argmax(1)]
            spread = np.where(np.isfinite(t), t, np.nan)
            merged = (np.nanmax(spread, 1) - np.nanmin(spread, 1)) < LASER_MERGE
        ok = tot > 0
        r[pix[ok]] = np.where(merged, mean, strongest)[ok]
        hit[pix[ok]] = True
    cos = np.where(np.isfinite(ren.cos_i), ren.cos_i, 1.0)
    sigma = scale * laser_sigma(np.where(hit, r, 1.0), cos, ren.reflectivity)
    out = r + sigma * z
    bad = ~hit | (u_drop < 0.0005) | ~(out > 0)
    return np.where(bad, np.nan, out)


def _tof(ren: Rendered, scale: float, rng: np.random.Generator) -> np.ndarray:
    N = ren.r0.size
    H, W = ren.shape
    z = rng.standard_normal(N)
    u_shiny = rng.random(N)
    r = ren.r0.copy()
    hit = np.isfinite(r)
    cos = np.where(hit, ren.cos_i, 1.0)
    rho = ren.reflectivity
    amp = np.where(hit, rho * cos / np.where(hit, r, 1.0) ** 2, 0.0)
    # Flying pixels: the pixel's footprint (its area plus the lens blur, +-0.6 px) adds the
    # returns' phasors; between two surfaces the phase lands between their ranges.
    pix = np.flatnonzero(_near_jump(ren, 1))
    if pix.size:
        t, c, rr = ren.footprint(pix, _grid_offsets(0.6))
        k = 4 * math.pi * TOF_FMOD / 299_792_458.0
        with np.errstate(invalid="ignore", divide="ignore"):
            a = np.where(np.isfinite(t), rr * c / t**2, 0.0)
            ph = np.where(np.isfinite(t), k * t, 0.0)
            re, im = (a * np.cos(ph)).sum(1), (a * np.sin(ph)).sum(1)
            ok = a.sum(1) > 0
            # Unwrap near the strongest return (the mixture never spans a whole wrap here).
            ref = ph[np.arange(pix.size), a.argmax(1)]
            dphi = np.angle((re + 1j * im) * np.exp(-1j * ref))
            rm = (ref + dphi) / k
        r[pix[ok]] = rm[ok]
        amp[pix[ok]] = np.hypot(re, im)[ok] / 9
        hit[pix[ok]] = True
    # Multipath: light bounced off the other wall of an inside corner arrives late.
    if ren.concave.any():
        d_px = distance_transform_edt(~ren.concave.reshape(H, W)).ravel()
        d_m = d_px * _pixel_size(np.where(hit, r, 1.0), ren.f)
        r = r + TOF_MULTIPATH * np.exp(-d_m / TOF_MULTIPATH_LEN) * hit
    sigma = scale * tof_sigma(np.where(hit, r, 1.0), cos, rho)
    out = r + sigma * z
    bad = ~hit | (amp < TOF_MIN_AMPLITUDE) | (ren.shiny & (u_shiny < 0.2)) | ~(out > 0)
    return np.where(bad, np.nan, out)


def _structured_light(ren: Rendered, scale: float, rng: np.random.Generator) -> np.ndarray:
    N = ren.r0.size
    H, W = ren.shape
    e_pix = rng.standard_normal(N)
    e_row = rng.standard_normal(H)
    u_fat = rng.random(N)
    u_drop = rng.random(N)
    z0 = _depth_of(ren)
    hit = np.isfinite(z0) & (z0 > 0)
    fb = ren.f * SL_BASELINE
    d = np.where(hit, fb / np.where(hit, z0, 1.0), 0.0)
    # The correlation window: at a jump the window is dominated by the nearer (textured,
    # brighter) surface, so the foreground grows by up to a pixel, raggedly.
    d2 = d.reshape(H, W)
    fat = d2.copy()
    fat[:, 1:] = np.maximum(fat[:, 1:], d2[:, :-1])
    fat[:, :-1] = np.maximum(fat[:, :-1], d2[:, 1:])
    fat[1:] = np.maximum(fat[1:], d2[:-1])
    fat[:-1] = np.maximum(fat[:-1], d2[1:])
    fat_d = fat.ravel()
    grow = _near_jump(ren, 1) & (fat_d > d * 1.02 + 0.3) & (u_fat < 0.5)
    d = np.where(grow, fat_d, d)
    rho = SL_ROW_SHARE
    noise = math.sqrt(1 - rho) * e_pix + math.sqrt(rho) * e_row[np.arange(N) // W]
    dq = np.round((d + scale * SL_SIGMA_D * noise) / SL_STEP) * SL_STEP
    with np.errstate(divide="ignore", invalid="ignore"):
        z = fb / dq
    ok = (hit | grow) & (dq > 0) & (z >= SL_RANGE[0]) & (z <= SL_RANGE[1])
    bad = ~ok | ren.shadow(SL_BASELINE) | (np.nan_to_num(ren.cos_i, nan=1.0) < 0.1)
    bad |= (ren.shiny & (u_drop < 0.5)) | (u_drop < 0.001)
    return np.where(bad, np.nan, z / ren.rays[:, 2])


def _stereo_field(shape: tuple[int, int], rng: np.random.Generator) -> np.ndarray:
    """Unit-robust-sigma correlated noise with heavy tails, (H, W)."""
    H, W = shape
    pad = 64
    w_blob, br, bc = STEREO_BLOB
    w_str, sr, sc = STEREO_STREAK
    e_row = rng.standard_normal(H)
    blob = rng.standard_normal((H, W))
    streak = rng.standard_normal((H + 4 * pad, W))
    white = rng.standard_normal((H, W))
    tail = rng.standard_normal((H, W))
    blob = _unit_field(_smooth(_smooth(blob, br, 1), bc, 0))
    streak = _unit_field(_ar_filter(_smooth(streak, sr, 1), sc, 0)[4 * pad:])
    F = (math.sqrt(STEREO_ROW_SHARE) * e_row[:, None] + math.sqrt(w_blob) * blob
         + math.sqrt(w_str) * streak + math.sqrt(STEREO_WHITE) * white)
    S = _unit_field(_smooth(_smooth(tail, STEREO_TAIL_LEN, 1), STEREO_TAIL_LEN, 0))
    F = F * np.exp(STEREO_TAIL * S)
    mad = float(np.median(np.abs(F - np.median(F)))) * 1.4826
    return F * (STEREO_TILE_GAIN / mad)


def _active_stereo(ren: Rendered, scale: float, cls: str,
                   rng: np.random.Generator) -> np.ndarray:
    N = ren.r0.size
    H, W = ren.shape
    F = _stereo_field((H, W), rng).ravel()
    blur = float(rng.uniform(*STEREO_EDGE_BLUR))
    hole_px = int(rng.integers(1, 3))
    u_hole = rng.random(N)
    dark = rng.standard_normal((H, W))
    z0 = _depth_of(ren)
    hit = np.isfinite(z0) & (z0 > 0)
    b = STEREO_BASELINE[cls]
    fb = ren.f * b
    # Edges rounded: blur the disparity (1/z is affine in the pixel coordinates on a plane, so
    # a symmetric blur leaves planes exact and rounds only creases and jumps).
    d = np.where(hit, fb / np.where(hit, z0, 1.0), 0.0).reshape(H, W)
    wgt = hit.reshape(H, W).astype(np.float64)
    num = _smooth(_smooth(d, blur, 1), blur, 0)
    den = _smooth(_smooth(wgt, blur, 1), blur, 0)
    with np.errstate(divide="ignore", invalid="ignore"):
        db = (num / den).ravel()
        z = fb / db
    z = z + scale * active_stereo_sigma(np.where(hit, z, 1.0), cls) * F
    # Holes: the left-right check fails next to jumps and where the second camera is
    # occluded; no pattern on dark patches or shiny tape.
    dark_f = _unit_field(_smooth(_smooth(dark, 5.0, 1), 5.0, 0)).ravel()
    bad = ~hit | ~(z >= STEREO_RANGE[0]) | (z > STEREO_RANGE[1])
    bad |= _near_jump(ren, hole_px) & (u_hole < 0.7)
    bad |= ren.shadow(b) | (dark_f > 2.6) | (ren.shiny & (u_hole < 0.8))
    bad |= np.nan_to_num(ren.cos_i, nan=1.0) < 0.1
    return np.where(bad, np.nan, z / ren.rays[:, 2])


def measure(sensor: str, ren: Rendered, scale: float, cls: str | None,
            rng: np.random.Generator) -> np.ndarray:
    """The measured range image of a render, (N,) float64 metres, NaN for no return.

    Parameters
    ----------
    sensor : str
        One of :data:`SENSORS`.
    ren : Rendered
        The noise-free render.
    scale : float
        Noise scale, times the sensor's nominal.
    cls : str or None
        The active-stereo class (:data:`STEREO_CLASSES`); unused by the others.
    rng : numpy.random.Generator
        The sensor's stream (the same stream gives the same image, bit for bit).
    """
    if sensor == "laser":
        return _laser(ren, scale, rng)
    if sensor == "tof":
        return _tof(ren, scale, rng)
    if sensor == "structured-light":
        return _structured_light(ren, scale, rng)
    if sensor == "active-stereo":
        return _active_stereo(ren, scale, cls or STEREO_CLASSES[0], rng)
    raise ValueError(f"unknown sensor {sensor!r}")
