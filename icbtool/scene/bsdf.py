"""Declared BSDFs: Mitsuba 3's plugins, their parameters, defaults and conventions.

A :class:`~icbtool.scene.Material` without a ``bsdf`` is icbtool's own two-sided Lambertian
material (albedo, texture, emission), traced by the tracer's fast kernel. A material whose
``bsdf`` is one of the dataclasses here is traced by the general kernel
(:mod:`icbtool.trace.general`) with that BSDF exactly as Mitsuba 3 evaluates, samples and weights
it; the material's ``albedo``/``texture`` then only stand in for it where no BSDF is evaluated
(the client's raster, the denoiser's albedo).

Names, parameters and defaults are Mitsuba 3's (``diffuse``, ``plastic``, ``roughplastic``,
``conductor``, ``roughconductor``, ``dielectric``, ``thindielectric``, ``roughdielectric``,
``twosided``, ``blendbsdf``, ``mask``, ``normalmap``, ``bumpmap``), and so are its conventions:
every BSDF but ``twosided``, the dielectrics and ``mask`` is one-sided (black seen from behind);
IORs are numbers or names of :data:`NAMED_IOR`; a conductor's ``material`` names a row of
:data:`CONDUCTOR_ETA_K` (the RGB eta and k Mitsuba's RGB variants use). A reflectance,
``alpha``, a blend ``weight`` or a mask ``opacity`` may be a :class:`Bitmap` or
:class:`Checkerboard` texture instead of a constant. ``normalmap`` and ``bumpmap`` evaluate
their nested BSDF in a shading frame tilted by a texture (the uv parametrisation's dp/du,
dp/dv), as Mitsuba 3.9 does.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, fields
from typing import Literal

import numpy as np

#: Index of refraction of Mitsuba 3's named materials (``int_ior="bk7"``...),
#: (mitsuba/render/ior.h).
NAMED_IOR: dict[str, float] = {
    "vacuum": 1.0,
    "helium": 1.000036,
    "hydrogen": 1.000132,
    "air": 1.000277,
    "carbon dioxide": 1.00045,
    "water": 1.333,
    "acetone": 1.36,
    "ethanol": 1.361,
    "carbon tetrachloride": 1.461,
    "glycerol": 1.4729,
    "benzene": 1.501,
    "silicone oil": 1.52045,
    "bromine": 1.661,
    "water ice": 1.31,
    "fused quartz": 1.458,
    "pyrex": 1.47,
    "acrylic glass": 1.49,
    "polypropylene": 1.49,
    "bk7": 1.5046,
    "sodium chloride": 1.544,
    "amber": 1.55,
    "pet": 1.575,
    "diamond": 2.419,
}

#: RGB (eta, k) of Mitsuba 3's named conductors (``material="Au"``...) as its RGB variants use
#: them (``mi.traverse(mi.load_dict({"type": "conductor", "material": name}))``; the test
#: suite checks the table against an installed Mitsuba). ``none``: a perfect mirror.
CONDUCTOR_ETA_K: dict[str, tuple[tuple[float, float, float], tuple[float, float, float]]] = {
    "a-C": (
        (2.9440457820892334, 2.2271363735198975, 1.968161702156067),
        (0.8874648809432983, 0.7992985248565674, 0.8152899742126465),
    ),
    "Ag": (
        (0.15527619421482086, 0.11672795563936234, 0.13838763535022736),
        (4.828354358673096, 3.122222423553467, 2.1469011306762695),
    ),
    "Al": (
        (1.6575008630752563, 0.8804047107696533, 0.521244466304779),
        (9.223811149597168, 6.26950216293335, 4.8370041847229),
    ),
    "AlAs": (
        (3.6052958965301514, 3.232937812805176, 2.2163186073303223),
        (0.0006794373039156199, 0.0, 0.007512709125876427),
    ),
    "AlSb": (
        (0.0, 4.139374732971191, 4.669254302978516),
        (0.0, 0.09400907903909683, 1.300570011138916),
    ),
    "Au": (
        (0.14303597807884216, 0.3753070831298828, 1.4420453310012817),
        (3.982996940612793, 2.38555645942688, 1.6033592224121094),
    ),
    "Be": (
        (4.185012340545654, 3.1850292682647705, 2.7840611934661865),
        (3.835465908050537, 3.010122299194336, 2.8689939975738525),
    ),
    "Cr": (
        (4.3696675300598145, 2.9165053367614746, 1.6549046039581299),
        (5.206546783447266, 4.231306076049805, 3.7546987533569336),
    ),
    "CsI": ((2.144899606704712, 1.7023189067840576, 1.6624271869659424), (0.0, 0.0, 0.0)),
    "Cu": (
        (0.2010054737329483, 0.9237495064735413, 1.1022154092788696),
        (3.913262128829956, 2.453045129776001, 2.14208984375),
    ),
    "Cu_palik": (
        (0.2132285088300705, 0.919715404510498, 1.1024107933044434),
        (3.9218733310699463, 2.457331657409668, 2.1365840435028076),
    ),
    "Cu2O": (
        (3.5517725944519043, 2.9498696327209473, 2.751875400543213),
        (0.11420702189207077, 0.19389685988426208, 0.6061338782310486),
    ),
    "CuO": (
        (3.2475409507751465, 2.447805166244507, 2.210219621658325),
        (0.5210895538330078, 0.5700307488441467, 0.7221789360046387),
    ),
    "d-C": ((2.7087197303771973, 2.3188257217407227, 2.2288975715637207), (0.0, 0.0, 0.0)),
    "Hg": (
        (2.3989386558532715, 1.4400279521942139, 0.9095703959465027),
        (6.327587127685547, 4.371924877166748, 3.4217636585235596),
    ),
    "HgTe": (
        (4.7790398597717285, 3.231196165084839, 2.6599011421203613),
        (1.6316126585006714, 1.5808104276657104, 1.7292873859405518),
    ),
    "Ir": (
        (3.0862998962402344, 2.08219051361084, 1.6179145574569702),
        (5.592153072357178, 4.0670881271362305, 3.2673120498657227),
    ),
    "K": (
        (0.06404318660497665, 0.046409767121076584, 0.038184914737939835),
        (2.1041996479034424, 1.3489400148391724, 0.9131258726119995),
    ),
    "Li": (
        (0.2657909393310547, 0.19561831653118134, 0.22094862163066864),
        (3.5401549339294434, 2.3111233711242676, 1.668607234954834),
    ),
    "MgO": (
        (2.0895838737487793, 1.6507234573364258, 1.5948790311813354),
        (4.332695226899608e-12, 0.0, 2.4986457347608848e-11),
    ),
    "Mo": (
        (4.483973979949951, 3.5251307487487793, 2.776310443878174),
        (4.1114373207092285, 3.4208269119262695, 3.1506073474884033),
    ),
    "Na_palik": (
        (0.06026935577392578, 0.056140948086977005, 0.061988431960344315),
        (3.1792733669281006, 2.11249041557312, 1.5790411233901978),
    ),
    "Nb": (
        (3.420073986053467, 2.790093183517456, 2.395629405975342),
        (3.441394567489624, 2.737666130065918, 2.5797457695007324),
    ),
    "Ni_palik": (
        (2.367304563522339, 1.6633731126785278, 1.4670780897140503),
        (4.498811721801758, 3.0501530170440674, 2.3454391956329346),
    ),
    "Rh": (
        (2.5857934951782227, 1.8602163791656494, 1.5542633533477783),
        (6.782260417938232, 4.702987194061279, 3.9760730266571045),
    ),
    "Se": (
        (4.058311462402344, 2.842935085296631, 2.8208534717559814),
        (0.75404953956604, 0.6384435296058655, 0.5218075513839722),
    ),
    "SiC": (
        (3.1723415851593018, 2.5259716510772705, 2.479370594024658),
        (7.537663577750209e-07, 0.0, 1.0192530680797063e-05),
    ),
    "SnTe": ((4.52424955368042, 1.9816449880599976, 1.2815912961959839), (0.0, 0.0, 0.0)),
    "Ta": (
        (2.062721014022827, 2.3929388523101807, 2.6279287338256836),
        (2.4083597660064697, 1.7414864301681519, 1.9470278024673462),
    ),
    "Te": (
        (7.390233516693115, 4.482104778289795, 2.637105941772461),
        (3.2560222148895264, 3.5270588397979736, 3.2920541763305664),
    ),
    "ThF4": ((1.8307136297225952, 1.4422285556793213, 1.3876476287841797), (0.0, 0.0, 0.0)),
    "TiC": (
        (3.700528383255005, 2.8374221324920654, 2.582287073135376),
        (3.2656350135803223, 2.3515892028808594, 2.17279052734375),
    ),
    "TiN": (
        (1.6484496593475342, 1.1505160331726074, 1.3798234462738037),
        (3.368328094482422, 1.943498134613037, 1.1020677089691162),
    ),
    "TiO2": (
        (3.4566099643707275, 2.8017358779907227, 2.905174970626831),
        (0.00010526483674766496, 0.0, 0.0006528865196742117),
    ),
    "VC": (
        (3.6575660705566406, 2.7527360916137695, 2.5326719284057617),
        (3.068300724029541, 2.1986873149871826, 1.9631927013397217),
    ),
    "V_palik": (
        (4.277582168579102, 3.512948751449585, 2.7610714435577393),
        (3.4913008213043213, 2.8894548416137695, 3.1115219593048096),
    ),
    "VN": (
        (2.8656022548675537, 2.1191890239715576, 1.9400911331176758),
        (3.0322425365448, 2.0561156272888184, 1.6163063049316406),
    ),
    "W": (
        (4.370816707611084, 3.300246477127075, 2.9984073638916016),
        (3.500640630722046, 2.6048738956451416, 2.27323317527771),
    ),
    "none": ((0.0, 0.0, 0.0), (1.0, 1.0, 1.0)),
}

Distribution = Literal["beckmann", "ggx"]
RGB = tuple[float, float, float]


def _rgb(x: object, what: str) -> RGB:
    a = np.asarray(x, np.float64).reshape(-1)
    if a.size == 1:
        a = np.repeat(a, 3)
    if a.shape != (3,) or not np.all(np.isfinite(a)):
        raise ValueError(f"{what} must be 1 or 3 finite numbers, got {x!r}")
    return (float(a[0]), float(a[1]), float(a[2]))


@dataclass(frozen=True, eq=False)
class Bitmap:
    """Mitsuba's ``bitmap`` texture: linear RGB texels, bilinear (or nearest), repeated.

    Attributes:
        data: (h, w, 3) float32 linear values (row 0 = the image's top, Mitsuba's v = 0).
        filter_type: ``bilinear`` (Mitsuba's default) or ``nearest``.
        path: the file it came from (messages, hashing), if any.
        to_uv: (3, 3) affine uv transform (``to_uv``), applied before the lookup.
    """

    data: np.ndarray
    filter_type: Literal["bilinear", "nearest"] = "bilinear"
    path: str | None = None
    to_uv: np.ndarray = field(default_factory=lambda: np.eye(3))

    def __post_init__(self) -> None:
        t = np.ascontiguousarray(self.data, np.float32)
        if t.ndim == 2:
            t = np.repeat(t[:, :, None], 3, 2)
        if t.ndim != 3 or t.shape[2] != 3 or t.shape[0] < 1 or t.shape[1] < 1:
            raise ValueError(f"bitmap texture must be (h, w, 3), got {np.shape(self.data)}")
        if not np.all(np.isfinite(t)):
            raise ValueError("bitmap texture has NaN/Inf texels")
        t.setflags(write=False)
        object.__setattr__(self, "data", t)
        if self.filter_type not in ("bilinear", "nearest"):
            raise ValueError(
                f"bitmap filter_type must be bilinear or nearest, got {self.filter_type!r}"
            )
        object.__setattr__(self, "to_uv", _affine(self.to_uv, "bitmap to_uv"))

    @property
    def mean(self) -> RGB:
        m = self.data.reshape(-1, 3).mean(0)
        return (float(m[0]), float(m[1]), float(m[2]))


@dataclass(frozen=True, eq=False)
class Checkerboard:
    """Mitsuba's ``checkerboard`` texture: ``color0`` where floor(2u) + floor(2v) is even in
    the (``to_uv``-transformed) uv square, else ``color1``; repeated."""

    color0: RGB = (0.4, 0.4, 0.4)
    color1: RGB = (0.2, 0.2, 0.2)
    to_uv: np.ndarray = field(default_factory=lambda: np.eye(3))

    def __post_init__(self) -> None:
        object.__setattr__(self, "color0", _rgb(self.color0, "checkerboard color0"))
        object.__setattr__(self, "color1", _rgb(self.color1, "checkerboard color1"))
        object.__setattr__(self, "to_uv", _affine(self.to_uv, "checkerboard to_uv"))

    @property
    def mean(self) -> RGB:
        return tuple(0.5 * (a + b) for a, b in zip(self.color0, self.color1))  # type: ignore[return-value]


def _affine(m: object, what: str) -> np.ndarray:
    a = np.asarray(m, np.float64)
    if a.shape == (4, 4):  # Mitsuba writes 2D transforms as 4x4 too: keep x, y, translation
        a = a[np.ix_([0, 1, 3], [0, 1, 3])]
    if a.shape != (3, 3) or not np.all(np.isfinite(a)):
        raise ValueError(f"{what} must be a finite 3x3 (or 4x4) matrix")
    a = np.ascontiguousarray(a)
    a.setflags(write=False)
    return a


Texture = Bitmap | Checkerboard
#: A parameter Mitsuba lets a texture drive: a constant (1 or 3 numbers) or a texture.
Spectrum = float | RGB | Texture


def _spectrum(x: object, what: str) -> Spectrum:
    if isinstance(x, (Bitmap, Checkerboard)):
        return x
    return _rgb(x, what)


def _scalar(x: object, what: str) -> float | Texture:
    if isinstance(x, (Bitmap, Checkerboard)):
        return x
    v = float(np.mean(np.asarray(x, np.float64)))
    if not math.isfinite(v):
        raise ValueError(f"{what} must be finite, got {x!r}")
    return v


def mean_of(x: Spectrum) -> RGB:
    """The mean colour of a constant or texture (what Mitsuba's ``Texture::mean`` returns)."""
    if isinstance(x, (Bitmap, Checkerboard)):
        return x.mean
    return _rgb(x, "value")


def ior_value(x: float | str, what: str) -> float:
    """An IOR given as a number or a name of :data:`NAMED_IOR`."""
    if isinstance(x, str):
        key = x.strip().lower()
        if key not in NAMED_IOR:
            raise ValueError(f"{what}: unknown IOR name {x!r} (known: {', '.join(NAMED_IOR)})")
        return NAMED_IOR[key]
    v = float(x)
    if not (math.isfinite(v) and v > 0):
        raise ValueError(f"{what} must be a positive number, got {x!r}")
    return v


def _check_distribution(d: str, what: str) -> None:
    if d not in ("beckmann", "ggx"):
        raise ValueError(f"{what} distribution must be 'beckmann' or 'ggx', got {d!r}")


def _check_alpha(a: object, what: str) -> None:
    if isinstance(a, (Bitmap, Checkerboard)):
        return
    if not (isinstance(a, float) and a >= 0):
        raise ValueError(f"{what} must be >= 0, got {a!r}")


def _check_interface(bsdf: object, spectra: tuple[str, ...]) -> None:
    """Resolve and check a dielectric interface's ``int_ior``/``ext_ior`` (names or numbers,
    which must differ) and its ``spectra`` fields, in place on the frozen ``bsdf``."""
    kind = type(bsdf).__name__.lower()
    for k in ("int_ior", "ext_ior"):
        object.__setattr__(bsdf, k, ior_value(getattr(bsdf, k), f"{kind} {k}"))
    if bsdf.int_ior == bsdf.ext_ior:  # type: ignore[attr-defined]
        raise ValueError(f"{kind}: int_ior and ext_ior must differ")
    for k in spectra:
        object.__setattr__(bsdf, k, _spectrum(getattr(bsdf, k), f"{kind} {k}"))


@dataclass(frozen=True, eq=False)
class Diffuse:
    """Mitsuba's ``diffuse``: one-sided Lambertian ``reflectance`` (default 0.5)."""

    reflectance: Spectrum = 0.5

    def __post_init__(self) -> None:
        object.__setattr__(self, "reflectance", _spectrum(self.reflectance, "diffuse reflectance"))


@dataclass(frozen=True, eq=False)
class _Coated:
    int_ior: float | str = "polypropylene"
    ext_ior: float | str = "air"
    diffuse_reflectance: Spectrum = 0.5
    specular_reflectance: Spectrum = 1.0
    nonlinear: bool = False

    def __post_init__(self) -> None:
        _check_interface(self, ("diffuse_reflectance", "specular_reflectance"))

    @property
    def eta(self) -> float:
        return float(self.int_ior) / float(self.ext_ior)


@dataclass(frozen=True, eq=False)
class Plastic(_Coated):
    """Mitsuba's ``plastic``: a diffuse base under a smooth dielectric coating (one-sided)."""


@dataclass(frozen=True, eq=False)
class RoughPlastic(_Coated):
    """Mitsuba's ``roughplastic``: a diffuse base under a rough dielectric coating (isotropic
    ``alpha``, one-sided)."""

    distribution: Distribution = "beckmann"
    alpha: float | Texture = 0.1

    def __post_init__(self) -> None:
        super().__post_init__()
        _check_distribution(self.distribution, "roughplastic")
        if isinstance(self.alpha, Bitmap | Checkerboard):
            raise ValueError("roughplastic alpha must be a number (as in Mitsuba 3), not a texture")
        object.__setattr__(self, "alpha", _scalar(self.alpha, "roughplastic alpha"))
        _check_alpha(self.alpha, "roughplastic alpha")


@dataclass(frozen=True, eq=False)
class Conductor:
    """Mitsuba's ``conductor``: a smooth metal mirror (one-sided); ``eta``/``k`` given, or
    those of the named ``material`` (:data:`CONDUCTOR_ETA_K`, default ``none``: all reflected)."""

    material: str = "none"
    eta: RGB | None = None
    k: RGB | None = None
    specular_reflectance: Spectrum = 1.0

    def __post_init__(self) -> None:
        kind = type(self).__name__.lower()
        if self.eta is None:
            if self.material not in CONDUCTOR_ETA_K:
                raise ValueError(
                    f"{kind}: unknown material {self.material!r} "
                    f"(known: {', '.join(CONDUCTOR_ETA_K)})"
                )
            eta, k = CONDUCTOR_ETA_K[self.material]
            object.__setattr__(self, "eta", eta)
            object.__setattr__(self, "k", k if self.k is None else _rgb(self.k, f"{kind} k"))
        else:
            object.__setattr__(self, "eta", _rgb(self.eta, f"{kind} eta"))
            object.__setattr__(self, "k", _rgb(0.0 if self.k is None else self.k, f"{kind} k"))
        object.__setattr__(
            self, "specular_reflectance",
            _spectrum(self.specular_reflectance, f"{kind} specular_reflectance"),
        )  # fmt: skip


@dataclass(frozen=True, eq=False)
class RoughConductor(Conductor):
    """Mitsuba's ``roughconductor``: microfacet metal, GGX or Beckmann, anisotropic
    ``alpha_u``/``alpha_v`` (``alpha`` sets both; default 0.1)."""

    distribution: Distribution = "beckmann"
    alpha_u: float | Texture = 0.1
    alpha_v: float | Texture = 0.1

    def __post_init__(self) -> None:
        super().__post_init__()
        _check_distribution(self.distribution, "roughconductor")
        for k in ("alpha_u", "alpha_v"):
            object.__setattr__(self, k, _scalar(getattr(self, k), f"roughconductor {k}"))
            _check_alpha(getattr(self, k), f"roughconductor {k}")


@dataclass(frozen=True, eq=False)
class Dielectric:
    """Mitsuba's ``dielectric``: a smooth interface (glass), reflecting and refracting."""

    int_ior: float | str = "bk7"
    ext_ior: float | str = "air"
    specular_reflectance: Spectrum = 1.0
    specular_transmittance: Spectrum = 1.0

    def __post_init__(self) -> None:
        _check_interface(self, ("specular_reflectance", "specular_transmittance"))

    @property
    def eta(self) -> float:
        return float(self.int_ior) / float(self.ext_ior)


@dataclass(frozen=True, eq=False)
class ThinDielectric(Dielectric):
    """Mitsuba's ``thindielectric``: a thin pane (inter-reflections summed, no refraction)."""


@dataclass(frozen=True, eq=False)
class RoughDielectric(Dielectric):
    """Mitsuba's ``roughdielectric``: a rough interface (Walter et al. 2007)."""

    distribution: Distribution = "beckmann"
    alpha_u: float | Texture = 0.1
    alpha_v: float | Texture = 0.1

    def __post_init__(self) -> None:
        super().__post_init__()
        _check_distribution(self.distribution, "roughdielectric")
        for k in ("alpha_u", "alpha_v"):
            object.__setattr__(self, k, _scalar(getattr(self, k), f"roughdielectric {k}"))
            _check_alpha(getattr(self, k), f"roughdielectric {k}")


@dataclass(frozen=True, eq=False)
class TwoSided:
    """Mitsuba's ``twosided``: ``front`` on both sides, or ``back`` on the back."""

    front: BSDF
    back: BSDF | None = None

    def __post_init__(self) -> None:
        for b in (self.front, self.back):
            if b is not None and not isinstance(b, BSDF_TYPES):
                raise ValueError(f"twosided: nested BSDF must be a BSDF, got {type(b).__name__}")
            if isinstance(b, (TwoSided,)):
                raise ValueError("twosided: a nested BSDF cannot be twosided again")


@dataclass(frozen=True, eq=False)
class BlendBSDF:
    """Mitsuba's ``blendbsdf``: ``(1 - weight) * bsdf0 + weight * bsdf1``."""

    bsdf0: BSDF
    bsdf1: BSDF
    weight: float | Texture = 0.5

    def __post_init__(self) -> None:
        object.__setattr__(self, "weight", _scalar(self.weight, "blendbsdf weight"))
        for b in (self.bsdf0, self.bsdf1):
            if not isinstance(b, BSDF_TYPES):
                raise ValueError(f"blendbsdf: nested BSDF must be a BSDF, got {type(b).__name__}")


@dataclass(frozen=True, eq=False)
class Mask:
    """Mitsuba's ``mask``: ``bsdf`` with probability ``opacity``, else the ray passes through."""

    bsdf: BSDF
    opacity: float | Texture = 0.5

    def __post_init__(self) -> None:
        object.__setattr__(self, "opacity", _scalar(self.opacity, "mask opacity"))
        if not isinstance(self.bsdf, BSDF_TYPES):
            raise ValueError(f"mask: nested BSDF must be a BSDF, got {type(self.bsdf).__name__}")


@dataclass(frozen=True, eq=False)
class NormalMap:
    """Mitsuba's ``normalmap``: ``bsdf`` evaluated in the shading frame tilted to the normal
    the ``normalmap`` texture encodes, ``2 * rgb - 1`` relative to the unperturbed shading frame
    (x along dp/du, z the shading normal): (0.5, 0.5, 1) leaves the surface as it is.

    Attributes:
        normalmap: the encoded normals, a texture (read as stored: Mitsuba asks for ``raw``
            bitmaps, with no sRGB decoding) or a constant colour.
        bsdf: the nested BSDF.
        flip_invalid_normals: mirror the perturbed normal's tangent part where the incident
            direction lies below it (Mitsuba's default, Schuessler et al. 2017).
        use_shadowing_function: scale the result by the microfacet shadowing term of Estevez
            et al. 2019, which softens the bump terminator (Mitsuba's default).
    """

    normalmap: Spectrum
    bsdf: BSDF
    flip_invalid_normals: bool = True
    use_shadowing_function: bool = True

    def __post_init__(self) -> None:
        object.__setattr__(self, "normalmap", _spectrum(self.normalmap, "normalmap normalmap"))
        _check_mapped(self.bsdf, "normalmap")


@dataclass(frozen=True, eq=False)
class BumpMap:
    """Mitsuba's ``bumpmap``: ``bsdf`` evaluated in the shading frame of the surface displaced
    along its shading normal by ``scale`` times ``texture`` (a height field over uv).

    The perturbed normal is ``dp_du' x dp_dv'`` with ``dp_du' = dp_du + n (scale * dh/du -
    n . dp_du)`` (and the same for v), ``dh/du`` the derivative of the texture's bilinear
    interpolant (of its luminance), as Mitsuba's ``eval_1_grad``; a ``nearest`` bitmap has no
    gradient.

    Attributes:
        texture: the height field, a bitmap.
        bsdf: the nested BSDF.
        scale: height scale (Mitsuba's default 1).
        flip_invalid_normals, use_shadowing_function: as :class:`NormalMap`.
    """

    texture: Bitmap
    bsdf: BSDF
    scale: float = 1.0
    flip_invalid_normals: bool = True
    use_shadowing_function: bool = True

    def __post_init__(self) -> None:
        if not isinstance(self.texture, Bitmap):
            raise ValueError(
                f"bumpmap texture must be a bitmap (Mitsuba has no gradient of other "
                f"textures), got {type(self.texture).__name__}"
            )
        s = float(self.scale)
        if not math.isfinite(s):
            raise ValueError(f"bumpmap scale must be finite, got {self.scale!r}")
        object.__setattr__(self, "scale", s)
        _check_mapped(self.bsdf, "bumpmap")


def _check_mapped(b: object, kind: str) -> None:
    if not isinstance(b, BSDF_TYPES):
        raise ValueError(f"{kind}: nested BSDF must be a BSDF, got {type(b).__name__}")


BSDF = (
    Diffuse | Plastic | RoughPlastic | Conductor | RoughConductor | Dielectric | ThinDielectric
    | RoughDielectric | TwoSided | BlendBSDF | Mask | NormalMap | BumpMap
)  # fmt: skip
BSDF_TYPES = (
    Diffuse, Plastic, RoughPlastic, Conductor, RoughConductor, Dielectric, ThinDielectric,
    RoughDielectric, TwoSided, BlendBSDF, Mask, NormalMap, BumpMap,
)  # fmt: skip
#: BSDFs that tilt the shading frame of the one they nest.
MAPPED_TYPES = (NormalMap, BumpMap)

#: Mitsuba plugin name of each BSDF class.
PLUGIN_NAMES: dict[type, str] = {
    Diffuse: "diffuse", Plastic: "plastic", RoughPlastic: "roughplastic",
    Conductor: "conductor", RoughConductor: "roughconductor", Dielectric: "dielectric",
    ThinDielectric: "thindielectric", RoughDielectric: "roughdielectric",
    TwoSided: "twosided", BlendBSDF: "blendbsdf", Mask: "mask", NormalMap: "normalmap",
    BumpMap: "bumpmap",
}  # fmt: skip


def plugin_name(b: BSDF) -> str:
    """Mitsuba's plugin name of a BSDF (``roughconductor``...)."""
    return PLUGIN_NAMES[type(b)]


def fresnel_dielectric(cos_i: float, eta: float) -> float:
    """Unpolarised Fresnel reflectance of a dielectric interface (Mitsuba's ``fresnel``):
    ``cos_i`` the cosine on the incident side (negative: from inside), ``eta`` = int/ext."""
    if eta == 1:
        return 0.0
    e = eta if cos_i >= 0 else 1.0 / eta
    c = abs(cos_i)
    s2 = (1 - c * c) / (e * e)
    if s2 >= 1:
        return 1.0
    ct = math.sqrt(1 - s2)
    rs = (c - e * ct) / (c + e * ct)
    rp = (e * c - ct) / (e * c + ct)
    return 0.5 * (rs * rs + rp * rp)


def approximate_albedo(b: BSDF) -> RGB:
    """A diffuse colour standing in for ``b`` where no BSDF is evaluated (the raster client,
    the denoiser's albedo): what it reflects or transmits at normal incidence."""
    if isinstance(b, Diffuse):
        return mean_of(b.reflectance)
    if isinstance(b, (Plastic, RoughPlastic)):
        f = fresnel_dielectric(1.0, b.eta)
        s, d = mean_of(b.specular_reflectance), mean_of(b.diffuse_reflectance)
        return tuple(f * a + (1 - f) * c for a, c in zip(s, d))  # type: ignore[return-value]
    if isinstance(b, Conductor):
        s = mean_of(b.specular_reflectance)
        out = []
        for c in range(3):
            e, k = b.eta[c], b.k[c]  # type: ignore[index]
            out.append(s[c] * ((e - 1) ** 2 + k * k) / ((e + 1) ** 2 + k * k))
        return tuple(out)  # type: ignore[return-value]
    if isinstance(b, Dielectric):
        f = fresnel_dielectric(1.0, b.eta)
        r, t = mean_of(b.specular_reflectance), mean_of(b.specular_transmittance)
        return tuple(f * a + (1 - f) * c for a, c in zip(r, t))  # type: ignore[return-value]
    if isinstance(b, TwoSided):
        return approximate_albedo(b.front)
    if isinstance(b, BlendBSDF):
        w = b.weight if isinstance(b.weight, float) else float(np.mean(b.weight.mean))
        a0, a1 = approximate_albedo(b.bsdf0), approximate_albedo(b.bsdf1)
        return tuple((1 - w) * x + w * y for x, y in zip(a0, a1))  # type: ignore[return-value]
    if isinstance(b, Mask | NormalMap | BumpMap):
        return approximate_albedo(b.bsdf)
    raise TypeError(f"not a BSDF: {type(b).__name__}")


def fingerprint(b: object) -> bytes:
    """Bytes that identify a BSDF or texture and all its parameters (scene hashing)."""
    if isinstance(b, np.ndarray):
        return str(b.shape).encode() + np.ascontiguousarray(b).tobytes()
    if isinstance(b, BSDF_TYPES + (Bitmap, Checkerboard)):
        parts = [type(b).__name__.encode()]
        for f in fields(b):
            if f.name == "path":
                continue
            parts.append(f.name.encode() + b"=" + fingerprint(getattr(b, f.name)))
        return b"(" + b",".join(parts) + b")"
    return repr(b).encode()


__all__ = [
    "BSDF", "BSDF_TYPES", "CONDUCTOR_ETA_K", "MAPPED_TYPES", "NAMED_IOR", "PLUGIN_NAMES",
    "BlendBSDF", "Bitmap", "BumpMap", "Checkerboard", "Conductor", "Dielectric", "Diffuse",
    "Mask", "NormalMap", "Plastic", "RoughConductor",
    "RoughDielectric", "RoughPlastic", "Spectrum", "Texture", "ThinDielectric", "TwoSided",
    "approximate_albedo", "fingerprint", "fresnel_dielectric", "ior_value", "mean_of",
    "plugin_name",
]  # fmt: skip
