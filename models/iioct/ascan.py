"""Synthetic iiOCT A-scans: what the fiber sees along its beam (frame S, z along the beam).

An A-scan is the magnitude of a complex depth profile sampled on `OctEngine.n_samples`
points over `depth_mm` of optical path in air. It holds the fiber-tip reflection at
`tip_offset_mm`, the retina (a specular inner limiting membrane followed by speckled
scattering layers) at optical path tip + n_g x distance, optional floaters, and complex
Gaussian noise. Amplitudes are in units of the noise RMS (E|noise|^2 = 1), so a
reflector's amplitude in dB is its SNR; the detector clips at `full_scale_db`.

Physics kept (each a real error source of the measured distance):
- group index of the vitreous: the optical path is n_g times the geometric one;
- axial PSF: Gaussian amplitude envelope, FWHM `psf_fwhm_um` of optical path in air;
- confocal gain of the ball lens: collected power 1 / (1 + ((d - working distance) /
  z_R)^2), z_R = pi w0^2 n_g / lambda, so the signal falls away from the 2 mm focus;
- incidence angle theta: the specular membrane falls as exp(-(theta / width)^2), the
  diffuse layers as cos(theta)^p; the beam crosses the layers obliquely (thicknesses
  stretched by 1 / cos theta) and its footprint (radius w(d)) spans a depth range
  w tan theta, which broadens the axial response;
- speckle: every scattering layer is a dense set of scatterers with circular complex
  Gaussian amplitudes, so its amplitude is Rayleigh/Rician distributed.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.special import erf, i0e, i1e

from models.shapes.validation import check_count, check_positive

# Vitreous at 1060 nm: phase index about 1.325 (water-like dispersion; Hammer et al.,
# JOSA A 16(9) 1999, measured vitreous dispersion 400-1100 nm), group index
# n_g = n - lambda dn/dlambda = 1.325 + 1.06 um x 0.0155 /um, about 1.345.
VITREOUS_GROUP_INDEX = 1.345
# Retinal tissue group index near 1 um (OCT literature: 1.36-1.40).
RETINA_GROUP_INDEX = 1.38
FWHM_PER_SIGMA = 2.0 * np.sqrt(2.0 * np.log(2.0))

# Retinal layers behind the inner limiting membrane (ILM): (name, start_um, end_um,
# RMS amplitude relative to the ILM), geometric depth across the layer at normal
# incidence. A perifoveal profile of about 310 um: bright nerve fibre layer, dark
# nuclear layers, bright ellipsoid zone and pigment epithelium, then choroid.
RETINA_LAYERS = (
    ("nerve fibre layer", 0.0, 40.0, 0.55),
    ("ganglion cell layer", 40.0, 80.0, 0.25),
    ("inner plexiform layer", 80.0, 115.0, 0.35),
    ("inner nuclear layer", 115.0, 150.0, 0.10),
    ("outer plexiform layer", 150.0, 175.0, 0.30),
    ("outer nuclear layer", 175.0, 255.0, 0.06),
    ("ellipsoid zone", 255.0, 270.0, 0.60),
    ("outer segments", 270.0, 290.0, 0.15),
    ("retinal pigment epithelium", 290.0, 310.0, 0.90),
    ("choroid", 310.0, 400.0, 0.35),
    ("deep choroid", 400.0, 500.0, 0.15),
)
RETINA_DEPTH_UM = RETINA_LAYERS[-1][2]
_SCATTERER_SPACING_UM = 5.0  # divides every layer edge; 6.9 um of optical path < PSF sigma / 2
_DEPTH_UM = np.arange(0.5 * _SCATTERER_SPACING_UM, RETINA_DEPTH_UM, _SCATTERER_SPACING_UM)
_LAYER_INDEX = np.searchsorted([hi for _, _, hi, _ in RETINA_LAYERS], _DEPTH_UM, side="right")


@dataclass(frozen=True)
class OctEngine:
    """The swept-source engine and fiber probe. Defaults: IOL Master 700-like engine
    (1060 nm, about 60 mm imaging depth in air, 30-40 um axial resolution) and a ball
    lens focused 2 mm in front of the tip.

    n_samples, depth_mm: A-scan length and the optical path in air it spans (mm);
    psf_fwhm_um: FWHM of the amplitude PSF along the optical path in air;
    group_index / retina_group_index: vitreous / retina group indices at the wavelength;
    tip_offset_mm: optical position of the fiber-tip reflection in the scan;
    tip_snr_db, retina_snr_db: tip reflection and ILM amplitude (retina in focus, normal
    incidence) over the noise RMS; full_scale_db: detector clipping level;
    working_distance_mm, beam_waist_um: focus distance and 1/e^2 waist radius in vitreous;
    specular_width_rad: angular width of the ILM's specular reflection;
    diffuse_exponent: p in the cos(theta)^p fall of the diffuse layers.
    """

    n_samples: int = 4096
    depth_mm: float = 60.0
    psf_fwhm_um: float = 35.0
    wavelength_nm: float = 1060.0
    group_index: float = VITREOUS_GROUP_INDEX
    retina_group_index: float = RETINA_GROUP_INDEX
    tip_offset_mm: float = 1.0
    tip_snr_db: float = 50.0
    retina_snr_db: float = 45.0
    full_scale_db: float = 60.0
    working_distance_mm: float = 2.0
    beam_waist_um: float = 30.0
    specular_width_rad: float = 0.2
    diffuse_exponent: float = 1.0

    def __post_init__(self):
        check_count(self, "n_samples", minimum=64)
        check_positive(self, "depth_mm", "psf_fwhm_um", "wavelength_nm", "tip_offset_mm", "tip_snr_db",
                       "retina_snr_db", "full_scale_db", "working_distance_mm", "beam_waist_um",
                       "specular_width_rad", "diffuse_exponent")
        for name in ("group_index", "retina_group_index"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and 1.0 <= v <= 2.0):
                raise ValueError(f"{name} must be a refractive index in [1, 2], got {v!r}")
        if self.tip_offset_mm >= 0.5 * self.depth_mm:
            raise ValueError(f"tip_offset_mm must be < depth_mm / 2 = {0.5 * self.depth_mm} mm, got {self.tip_offset_mm}")
        if self.psf_fwhm_um * 1e-3 < self.sample_spacing_mm:
            raise ValueError(f"psf_fwhm_um = {self.psf_fwhm_um} is below the sample spacing "
                             f"{self.sample_spacing_mm * 1e3:.1f} um: the PSF would be undersampled")
        if max(self.tip_snr_db, self.retina_snr_db) >= self.full_scale_db:
            raise ValueError(f"full_scale_db must exceed tip_snr_db and retina_snr_db, got {self.full_scale_db}")

    @property
    def sample_spacing_mm(self) -> float:
        """Optical path in air per sample (mm)."""
        return self.depth_mm / self.n_samples

    @property
    def psf_sigma_mm(self) -> float:
        """Standard deviation of the Gaussian amplitude PSF (mm of optical path in air)."""
        return self.psf_fwhm_um * 1e-3 / FWHM_PER_SIGMA

    @property
    def full_scale(self) -> float:
        """Clipping level of the detector, in noise-RMS units."""
        return 10.0 ** (self.full_scale_db / 20.0)

    @property
    def rayleigh_range_mm(self) -> float:
        """Rayleigh range of the probe beam in vitreous, pi w0^2 n_g / lambda (mm)."""
        return np.pi * (self.beam_waist_um * 1e-3) ** 2 * self.group_index / (self.wavelength_nm * 1e-6)

    @property
    def max_distance_mm(self) -> float:
        """Largest tip-retina distance (mm) whose whole retinal profile fits in the scan."""
        tail = RETINA_DEPTH_UM * 1e-3 * self.retina_group_index + 6.0 * self.psf_sigma_mm
        return (self.depth_mm - self.tip_offset_mm - tail) / self.group_index

    def optical_position_mm(self, distance_mm):
        """Position in the scan (mm of optical path in air) of a reflector `distance_mm`
        (geometric, in vitreous) in front of the tip."""
        return self.tip_offset_mm + self.group_index * np.asarray(distance_mm, dtype=float)

    def confocal_gain(self, distance_mm):
        """Amplitude factor of the ball lens's confocal gate at `distance_mm` (1 at focus)."""
        u = (np.asarray(distance_mm, dtype=float) - self.working_distance_mm) / self.rayleigh_range_mm
        return 1.0 / np.sqrt(1.0 + u * u)  # amplitude = sqrt(collected power)

    def beam_radius_mm(self, distance_mm):
        """1/e^2 radius of the beam at `distance_mm` from the tip (mm)."""
        u = (np.asarray(distance_mm, dtype=float) - self.working_distance_mm) / self.rayleigh_range_mm
        return self.beam_waist_um * 1e-3 * np.sqrt(1.0 + u * u)


@dataclass(frozen=True)
class Floater:
    """A vitreous opacity on the beam: a thin scattering sheet `distance_mm` in front of
    the tip, `thickness_um` thick (geometric, thinner than the PSF), whose reflection
    peaks at an RMS amplitude of `snr_db` over the noise floor (before the confocal gain)."""

    distance_mm: float
    snr_db: float = 30.0
    thickness_um: float = 10.0

    def __post_init__(self):
        check_positive(self, "distance_mm", "snr_db", "thickness_um")


def _check_geometry(distance_mm, incidence_rad) -> tuple[float, float]:
    d, th = float(distance_mm), float(incidence_rad)
    if not np.isfinite(d) or d <= 0.0:
        raise ValueError(f"distance_mm must be finite and > 0, got {distance_mm!r}")
    if not np.isfinite(th) or not 0.0 <= th < 0.5 * np.pi:
        raise ValueError(f"incidence_rad must be in [0, pi/2), got {incidence_rad!r}")
    return d, th


def axial_sigma_mm(engine: OctEngine, distance_mm: float, incidence_rad):
    """Sigma (mm of optical path) of the retina's axial response: the PSF broadened by the
    depth range the beam footprint (radius w at `distance_mm`) spans on a retina tilted by
    `incidence_rad`. A scatterer at lateral offset x is weighted exp(-2 x^2 / w^2) in
    amplitude (illumination x collection), i.e. sigma_x = w / 2, at depth x tan(theta).
    `incidence_rad` may be an array (then so is the result)."""
    th = np.asarray(incidence_rad, dtype=float)
    d, _ = _check_geometry(distance_mm, th.max() if th.size else 0.0)
    if th.size and th.min() < 0.0:
        raise ValueError(f"incidence_rad must be in [0, pi/2), got {incidence_rad!r}")
    spread = 0.5 * float(engine.beam_radius_mm(d)) * np.tan(th) * engine.group_index
    return np.hypot(engine.psf_sigma_mm, spread) if th.ndim else float(np.hypot(engine.psf_sigma_mm, spread))


def _rician_mean(nu: np.ndarray, power: np.ndarray) -> np.ndarray:
    """E|nu + speckle| for a deterministic amplitude `nu` plus circular complex Gaussian
    speckle of mean power `power` (the Rician mean)."""
    x = nu * nu / np.maximum(power, 1e-300)
    with np.errstate(over="ignore", invalid="ignore"):
        rician = 0.5 * np.sqrt(np.pi * power) * ((1.0 + x) * i0e(0.5 * x) + x * i1e(0.5 * x))
    return np.where(x < 1e8, rician, nu)


@dataclass(frozen=True, eq=False)
class RetinaResponse:
    """The retina's axial response behind its ILM: a deterministic ILM reflection of
    amplitude `ilm_amplitude` and speckled layers between `layer_edges_mm` (L, 2)
    (optical path behind the ILM, mm) of RMS amplitude `layer_rms` (L,) (noise-RMS units,
    for a layer much thicker than the response), all seen through a Gaussian axial
    response of sigma `sigma_mm`; `stretch` converts um of tissue to mm of optical path."""

    ilm_amplitude: float
    layer_edges_mm: np.ndarray
    layer_rms: np.ndarray
    sigma_mm: float
    stretch: float

    def scatterers(self) -> tuple[np.ndarray, np.ndarray]:
        """(z, rms): optical positions behind the ILM (N,) mm and RMS amplitudes (N,) of
        discrete scatterers equivalent to the layers (entry 0: the ILM). A layer of RMS a
        sampled every ds carries a^2 ds / integral(h^2) = a^2 ds / (sigma sqrt(pi)) each."""
        ds = _SCATTERER_SPACING_UM * self.stretch
        per = np.sqrt(ds / (self.sigma_mm * np.sqrt(np.pi)))
        z = np.concatenate([[0.0], _DEPTH_UM * self.stretch])
        return z, np.concatenate([[self.ilm_amplitude], per * self.layer_rms[_LAYER_INDEX]])

    def mean_amplitude(self, z_mm) -> np.ndarray:
        """Expected (speckle-averaged, noise-free) amplitude at optical positions `z_mm`
        behind the ILM: the Rician mean of the ILM over the layers' speckle power."""
        z = np.asarray(z_mm, dtype=float)[..., None]
        s = self.sigma_mm
        power = 0.5 * (erf((z - self.layer_edges_mm[:, 0]) / s) - erf((z - self.layer_edges_mm[:, 1]) / s)) @ self.layer_rms ** 2
        nu = self.ilm_amplitude * np.exp(-0.5 * (z[..., 0] / s) ** 2)
        return _rician_mean(nu, power)


def retina_layers(engine: OctEngine, incidence_rad: float, sigma_mm: float, scale: float = 1.0) -> RetinaResponse:
    """The retina's response at `incidence_rad` seen through an axial sigma `sigma_mm`:
    layers stretched by 1 / cos(theta) (the beam crosses them obliquely), the specular ILM
    falling as exp(-(theta / width)^2), the diffuse layers as cos(theta)^p; amplitudes x
    `scale` x sqrt(psf sigma / sigma_mm), so broadening conserves the reflected energy."""
    th = float(incidence_rad)
    stretch = engine.retina_group_index / np.cos(th) * 1e-3  # um of tissue -> mm of optical path
    a = scale * np.sqrt(engine.psf_sigma_mm / sigma_mm)
    return RetinaResponse(
        ilm_amplitude=a * float(np.exp(-(th / engine.specular_width_rad) ** 2)),
        layer_edges_mm=np.array([(lo, hi) for _, lo, hi, _ in RETINA_LAYERS]) * stretch,
        layer_rms=a * np.cos(th) ** engine.diffuse_exponent * np.array([rms for *_, rms in RETINA_LAYERS]),
        sigma_mm=float(sigma_mm),
        stretch=stretch,
    )


def retina_response(engine: OctEngine, distance_mm: float, incidence_rad: float) -> RetinaResponse:
    """The retina's response for the retina `distance_mm` in front of the tip at
    `incidence_rad`, in noise-RMS units (retina SNR x confocal gain)."""
    d, th = _check_geometry(distance_mm, incidence_rad)
    scale = 10.0 ** (engine.retina_snr_db / 20.0) * float(engine.confocal_gain(d))
    return retina_layers(engine, th, axial_sigma_mm(engine, d, th), scale)


def _add_response(signal: np.ndarray, touched: np.ndarray, engine: OctEngine, z_mm: np.ndarray, amp: np.ndarray,
                  sigma: float) -> None:
    """signal += sum_j amp_j exp(-(z_k - z_j)^2 / (2 sigma^2)) on the samples k within
    6 sigma of the scatterers (z: optical positions in the scan, mm), marked in `touched`."""
    dz = engine.sample_spacing_mm
    k0 = max(int(np.floor((z_mm.min() - 6.0 * sigma) / dz)), 0)
    k1 = min(int(np.ceil((z_mm.max() + 6.0 * sigma) / dz)) + 1, engine.n_samples)
    if k1 <= k0:
        return
    u = (np.arange(k0, k1) * dz)[:, None] - z_mm[None, :]
    u *= u
    u *= -0.5 / (sigma * sigma)
    ri = np.exp(u, out=u) @ np.column_stack([amp.real, amp.imag])  # real GEMM: 2x cheaper than complex
    signal.real[k0:k1] += ri[:, 0]
    signal.imag[k0:k1] += ri[:, 1]
    touched[k0:k1] = True


def _complex_normal(rng, n: int) -> np.ndarray:
    """n circular complex Gaussian samples with E|x|^2 = 1."""
    return rng.standard_normal(2 * n).view(complex) * np.sqrt(0.5)


def synthesize_ascan(
    distance_mm: float,
    incidence_rad: float = 0.0,
    rng=None,
    *,
    engine: OctEngine = OctEngine(),
    floaters=(),
    gain_db: float = 0.0,
) -> np.ndarray:
    """One A-scan (n_samples,) of amplitudes in noise-RMS units, clipped at full scale,
    for the retina `distance_mm` (geometric, along the beam, from the tip) in front of
    the tip, hit at `incidence_rad` in [0, pi/2) from its normal.

    `rng`: numpy Generator or seed (speckle and noise); `floaters`: Floater objects;
    `gain_db`: detector gain applied to every reflection (the noise floor stays at 1),
    so a large gain saturates the scan. A retina beyond the imaging depth is simply absent.
    """
    d, th = _check_geometry(distance_mm, incidence_rad)
    gain = 10.0 ** (float(gain_db) / 20.0)
    if not np.isfinite(gain):
        raise ValueError(f"gain_db must be finite, got {gain_db!r}")
    for f in floaters:
        if not isinstance(f, Floater):
            raise ValueError(f"floaters must hold Floater objects, got {type(f).__name__}")
    rng = np.random.default_rng(rng)
    n = engine.n_samples
    signal = np.zeros(n, dtype=complex)
    touched = np.zeros(n, dtype=bool)
    psf = engine.psf_sigma_mm
    tip_amp = gain * 10.0 ** (engine.tip_snr_db / 20.0)
    _add_response(signal, touched, engine, np.array([engine.tip_offset_mm]), np.array([tip_amp + 0j]), psf)

    retina = retina_response(engine, d, th)
    z, rms = retina.scatterers()
    speckle = _complex_normal(rng, len(z))
    speckle[0] = 1.0  # the ILM is one deterministic reflector
    _add_response(signal, touched, engine, engine.optical_position_mm(d) + z, gain * rms * speckle, retina.sigma_mm)

    for f in floaters:
        zf = np.arange(0.0, f.thickness_um, _SCATTERER_SPACING_UM) * 1e-3
        each = gain * 10.0 ** (f.snr_db / 20.0) * float(engine.confocal_gain(f.distance_mm)) / np.sqrt(len(zf))
        _add_response(signal, touched, engine, engine.optical_position_mm(f.distance_mm + zf),
                      each * _complex_normal(rng, len(zf)), psf)

    # |complex noise|^2 ~ Exp(1) where there is no signal; the full complex sum elsewhere
    out = np.sqrt(rng.standard_exponential(n))
    k = np.flatnonzero(touched)
    out[k] = np.abs(signal[k] + _complex_normal(rng, len(k)))
    np.minimum(out, engine.full_scale, out=out)
    return out
