"""The rig calibration file (rigs.yaml): per rig, the wide and narrow cameras and E^sl.

```yaml
units: meters
rigs:
  - name: rig01
    sensors:
      wide:   {model: OPENCV, width: 1624, height: 1234, params: [fx, fy, cx, cy, k1, k2, p1, p2]}
      narrow: {model: OPENCV, width: 1624, height: 1234, params: [...]}
    narrow_from_wide:          # x_narrow = R x_wide + t, metres (OpenCV stereoCalibrate's R, T)
      rotation: [[...], [...], [...]]
      translation: [tx, ty, tz]
```
Intrinsics use COLMAP's pixel convention (first pixel centre at (0.5, 0.5)). Optional uncertainty keys
(``sigmas`` per sensor; ``sigma_rotation_deg``, ``sigma_translation_m``, ``covariance`` under
``narrow_from_wide``), written by ``rigsfm calibrate``, become :class:`RigSigmas` on ``RigCalibration.sigmas``.

Besides the syntax, :func:`load_rigs` refuses what cannot be a real rig, one line naming the rig, the key and
the fix: unknown keys (with a "did you mean"), an E^sl baseline outside 1 mm - 5 m (millimetres written as
metres), a principal point outside the image, a focal length implausible for the image width, an image size no
camera has, lens parameters outside their model's domain or bending the image centre beyond any lens, sigmas that
are not positive, finite and plausible, a key given twice, and rig names that are equal once Unicode-normalised
(NFC: macOS writes folder names decomposed, editors compose them).
"""

from __future__ import annotations

import copy
import difflib
import math
import numbers
import unicodedata
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pycolmap
import yaml

from rigsfm.core.errors import InputError
from rigsfm.core.io import load_yaml_or_json, write_text_atomic
from rigsfm.core.names import SENSORS
from rigsfm.core.serialise import camera_to_dict, pose_to_dict

# Every COLMAP model with a focal length and a principal point (EQUIRECTANGULAR has neither: no rig camera).
CAMERA_MODELS = tuple(m for m in pycolmap.CameraModelId.__members__ if m not in ("INVALID", "EQUIRECTANGULAR"))
ROTATION_TOLERANCE = 1e-5

# Plausibility limits (see load_rigs): what lies outside is a unit or typing mistake, not a rig.
BASELINE_RANGE_M = (0.001, 5.0)  # |t| of E^sl: two cameras on one rig
# focal length / image width: a 220-degree fisheye is ~0.2, a 150-degree perspective lens ~0.13; long narrow
# lenses are 3-10 (a 1200 mm lens on a 1/2.3" sensor ~200 would be refused: not a camera for this task)
FOCAL_RANGE_WIDTHS = (0.1, 50.0)
FOCAL_ASPECT_RANGE = (1 / 3, 3.0)  # fx / fy: anamorphic lenses reach 2
MAX_SIGMA_ROTATION_DEG = 5.0
MAX_SIGMA_FOCAL = 0.10  # relative to the focal length
MAX_SIGMA_PRINCIPAL_POINT = 0.10  # relative to the image size
# below these a calibration claims more than any board gives, and the adjustment's weights overflow
MIN_SIGMA_FOCAL_PX = 1e-4
MIN_SIGMA_ROTATION_DEG = 1e-6
MIN_SIGMA_TRANSLATION_M = 1e-7
MAX_IMAGE_SIDE = 100_000  # pixels: the largest sensors have ~20 000; COLMAP keeps sizes in C++ ints
MAX_RIGS = 10_000  # a network far beyond any mapped with rigsfm: more is a wrong file
MAX_RIGS_FILE_BYTES = 32 << 20  # ~1 KB a rig with every sigma and covariance: MAX_RIGS fit 3x over
# Lens parameters with a bounded domain (COLMAP's models): EUCM's alpha in [0, 1] and beta > 0; FOV's omega, the
# field of view in radians, in (0, pi).
PARAM_RANGES = {("EUCM", "alpha"): (0.0, 1.0), ("EUCM", "beta"): (1e-6, 100.0), ("FOV", "omega"): (1e-6, np.pi)}
MAX_DISTORTION_COEFFICIENT = 1e3  # |k|, |p|, |s|: real fits stay within ~10; 1e6 is a typo
# Within this fraction of the shorter image side around the principal point, where every lens (fisheyes
# included) images, the ray angle must grow outwards and stay within this factor of the pinhole's angle.
CENTRE_FRACTION = 0.25
CENTRE_ANGLE_RATIO = (0.5, 2.0)

TOP_KEYS = ("units", "rigs")
RIG_KEYS = ("name", "sensors", "narrow_from_wide")
CAMERA_KEYS = ("model", "width", "height", "params", "sigmas")
POSE_KEYS = ("rotation", "translation", "sigma_rotation_deg", "sigma_translation_m", "covariance")


@dataclass
class RigSigmas:
    """1-sigma uncertainties of one rig's calibration (None: not estimated, nothing written).

    ``wide``/``narrow``: one per entry of the camera's params (COLMAP order and pixels; 0 = held fixed, allowed
    for distortion terms only). ``rotation_deg``: per axis of w with R_true = Exp(w) R (a small rotation applied
    on the left, degrees). ``translation_m``: of t. ``covariance``: 6x6 of [w (rad), t (m)]."""

    wide: np.ndarray | None = None
    narrow: np.ndarray | None = None
    rotation_deg: np.ndarray | None = None
    translation_m: np.ndarray | None = None
    covariance: np.ndarray | None = None
    notes: list[str] = field(default_factory=list)  # why something is missing (rigsfm calibrate's report)

    def sensor(self, name: str) -> np.ndarray | None:
        return self.wide if name == "wide" else self.narrow

    def is_empty(self) -> bool:
        return all(v is None for v in (self.wide, self.narrow, self.rotation_deg, self.translation_m,
                                       self.covariance))


@dataclass(frozen=True)
class RigCalibration:
    """One hybrid rig: its two calibrated cameras and ``narrow_from_wide`` (E^sl, metres); ``sigmas`` their
    uncertainties when rigs.yaml gives them (None otherwise)."""

    name: str
    wide: pycolmap.Camera
    narrow: pycolmap.Camera
    narrow_from_wide: pycolmap.Rigid3d
    sigmas: RigSigmas | None = field(default=None, compare=False)

    def camera(self, sensor: str) -> pycolmap.Camera:
        return self.wide if sensor == "wide" else self.narrow


def nfc(name: str) -> str:
    """``name`` in Unicode's composed form (NFC), the one form in which names are compared: macOS writes folder
    and file names decomposed (NFD), which an editor's composed 'é' in rigs.yaml would otherwise not match."""
    return unicodedata.normalize("NFC", name)


def check_keys(spec: dict, known: Sequence[str], where: str) -> None:
    """Refuse a key that is not in ``known``, suggesting the closest known one (a typo is never ignored)."""
    for key in spec:
        if key in known:
            continue
        if isinstance(key, numbers.Integral) and not isinstance(key, bool) and spec[key] is None:
            raise InputError(f"{where}: unknown key {key!r} with no value: a decimal comma? Inside {{...}} or [...], "
                             f"a comma separates values ('25,{key}' is 25 and {key}); write decimals with a point "
                             f"(25.{key})")
        hint = difflib.get_close_matches(str(key), [str(k) for k in known], n=1, cutoff=0.5)
        raise InputError(f"{where}: unknown key {key!r}" + (f" (did you mean {hint[0]!r}?)" if hint else "")
                         + f"; the keys here are {', '.join(known)}")


def parse_camera(spec, where: str) -> pycolmap.Camera:
    """A ``pycolmap.Camera`` from ``{model, width, height, params}``; ``where`` names it in errors."""
    if not isinstance(spec, dict):
        raise InputError(f"{where}: expected a mapping with model, width, height, params")
    check_keys(spec, CAMERA_KEYS, where)
    missing = [k for k in ("model", "width", "height", "params") if k not in spec]
    if missing:
        raise InputError(f"{where}: missing {', '.join(missing)}")
    model = str(spec["model"]).upper()
    if model not in CAMERA_MODELS:
        raise InputError(
            f"{where}: unknown camera model {spec['model']!r}; use one of {', '.join(CAMERA_MODELS)}"
        )
    for key in ("width", "height"):
        value = spec[key]
        # the range first: float() of an integer beyond a float's range raises OverflowError
        if isinstance(value, bool) or not isinstance(value, numbers.Real) \
                or not 0 < value <= MAX_IMAGE_SIDE or not float(value).is_integer():  # type: ignore[operator]  # typeshed: numbers.Real has no <
            raise InputError(f"{where}: {key} must be a whole number of pixels, 1 to {MAX_IMAGE_SIDE}, got "
                             f"{_short(value)}")
    width, height = int(spec["width"]), int(spec["height"])
    try:
        params = [float(p) for p in spec["params"]]
    except (TypeError, ValueError, OverflowError) as e:
        raise InputError(f"{where}: params must be a list of numbers, got {_short(spec['params'])}") from e
    camera = pycolmap.Camera(model=model, width=width, height=height, params=params)
    expected = [p.strip() for p in camera.params_info.split(",")]
    if len(params) != len(expected):
        raise InputError(
            f"{where}: camera model {model} takes {len(expected)} params ({', '.join(expected)}), "
            f"got {len(params)}"
        )
    if not all(math.isfinite(p) for p in params) or min(camera.focal_length_x, camera.focal_length_y) <= 0:
        raise InputError(f"{where}: params must be finite with positive focal lengths")
    check_plausible_camera(camera, where)
    check_lens(camera, where)
    return camera


_KINDS = {"int": "a number", "float": "a number", "bool": "true/false", "list": "a list", "dict": "a mapping",
          "date": "a date", "datetime": "a date", "bytes": "binary data"}


def _short(value, limit: int = 40) -> str:
    """``repr(value)``, cut to ``limit`` characters (a 300-digit number is not repeated back in full)."""
    text = repr(value) if not isinstance(value, int) or isinstance(value, bool) or abs(value) < 10**30 \
        else f"a {len(str(abs(value)))}-digit number"
    return text if len(text) <= limit else text[:limit - 3] + "..."


# check_lens's probe: 4 rays out from the principal point (+x, -x, +y, -y), 8 steps each, as fractions of its reach
_LENS_STEPS = 8
_LENS_OFFSETS = (np.array([[1.0, 0.0], [-1.0, 0.0], [0.0, 1.0], [0.0, -1.0]])[:, None, :]
                 * np.linspace(0.0, 1.0, _LENS_STEPS + 1)[1:][None, :, None]).reshape(-1, 2)


def check_lens(camera: pycolmap.Camera, where: str) -> None:
    """Refuse lens parameters outside their model's domain (EUCM alpha, FOV omega), absurd distortion
    coefficients, and a model that bends the image centre beyond any lens: around the principal point every
    lens, fisheyes included, images, and there the ray angle grows outwards within a factor of 2 of the
    pinhole's (k1 = 1e6 squeezes it to nothing; a runaway polynomial folds it back)."""
    model = camera.model.name
    names = [p.strip() for p in camera.params_info.split(",")]
    params = np.asarray(camera.params, dtype=np.float64)
    for name, value in zip(names, params, strict=True):
        if (model, name) in PARAM_RANGES:
            low, high = PARAM_RANGES[(model, name)]
            if not low <= value <= high:
                raise InputError(f"{where}: {model}'s {name} = {value:g} lies outside its domain {low:g} - {high:g}; "
                                 "check the params' order and values")
        elif name[0] in "kps" and abs(value) > MAX_DISTORTION_COEFFICIENT:
            raise InputError(f"{where}: distortion coefficient {name} = {value:g} is beyond any lens (real ones stay "
                             f"within ~10, at most {MAX_DISTORTION_COEFFICIENT:g}); check the params' order and digits")
    cx, cy = camera.principal_point_x, camera.principal_point_y
    reach = CENTRE_FRACTION * min(camera.width, camera.height)
    pixels = np.array([cx, cy]) + reach * _LENS_OFFSETS
    focal = np.array([camera.focal_length_x, camera.focal_length_x, camera.focal_length_y, camera.focal_length_y])
    with np.errstate(all="ignore"):
        rays = np.asarray(camera.cam_ray_from_img(pixels), dtype=np.float64).reshape(4, _LENS_STEPS, 3)
        angles = np.arctan2(np.hypot(rays[..., 0], rays[..., 1]), rays[..., 2])
        ratio = angles[:, -1] / np.arctan(reach / focal)
    if not (np.isfinite(angles).all() and (angles[:, 1:] > angles[:, :-1]).all()
            and ((CENTRE_ANGLE_RATIO[0] <= ratio) & (ratio <= CENTRE_ANGLE_RATIO[1])).all()):
        raise InputError(f"{where}: these {model} params ({', '.join(f'{n}={v:g}' for n, v in zip(names, params))}) "
                         "bend the image centre beyond any lens (the rays there do not spread as a lens's do); "
                         "check the distortion coefficients' order, signs and digits")


def check_plausible_camera(camera: pycolmap.Camera, where: str) -> None:
    """Refuse a principal point outside the image and a focal length no lens has at this image size."""
    cx, cy = camera.principal_point_x, camera.principal_point_y
    if not (0.0 <= cx <= camera.width and 0.0 <= cy <= camera.height):
        raise InputError(
            f"{where}: principal point ({cx:g}, {cy:g}) lies outside the {camera.width}x{camera.height} image; "
            "give cx, cy in pixels of this image size (COLMAP order: after the focal length)")
    low, high = FOCAL_RANGE_WIDTHS
    for axis, focal in (("x", camera.focal_length_x), ("y", camera.focal_length_y)):
        ratio = focal / camera.width
        if not low <= ratio <= high:
            raise InputError(
                f"{where}: focal length f{axis} = {focal:g} px is {ratio:.3g} x the image width {camera.width}; "
                f"a lens has {low:g}-{high:g} x (fisheye ~0.2, long lenses 3-10): give it in pixels of this image "
                "size, not millimetres")
    aspect = camera.focal_length_x / camera.focal_length_y
    if not FOCAL_ASPECT_RANGE[0] <= aspect <= FOCAL_ASPECT_RANGE[1]:
        raise InputError(f"{where}: fx / fy = {aspect:.3g}; pixels are (nearly) square, so fx and fy should be "
                         "close: check the params' order and digits")


def parse_rigid3d(spec, where: str) -> pycolmap.Rigid3d:
    """``{rotation: 3x3, translation: 3}`` -> ``pycolmap.Rigid3d``, checking it is a proper rotation."""
    if isinstance(spec, dict):
        check_keys(spec, POSE_KEYS, where)
    if not isinstance(spec, dict) or "rotation" not in spec or "translation" not in spec:
        raise InputError(f"{where}: expected a mapping with rotation (3x3) and translation (3)")
    try:
        rotation = np.array(spec["rotation"], dtype=np.float64)
        translation = np.array(spec["translation"], dtype=np.float64).reshape(-1)
    except (TypeError, ValueError, OverflowError) as e:
        raise InputError(f"{where}: rotation and translation must be numbers") from e
    if rotation.shape != (3, 3) or translation.shape != (3,):
        raise InputError(
            f"{where}: rotation must be 3x3 and translation 3 numbers, "
            f"got {rotation.shape} and {translation.shape}"
        )
    if not (np.isfinite(rotation).all() and np.isfinite(translation).all()):
        raise InputError(f"{where}: rotation and translation must be finite")
    orthonormality = float(np.abs(rotation.T @ rotation - np.eye(3)).max())
    if orthonormality > ROTATION_TOLERANCE:
        raise InputError(
            f"{where}: rotation is not orthonormal (max |R^T R - I| = {orthonormality:.2g}); "
            "give the full-precision rotation matrix, e.g. from cv2.stereoCalibrate or cv2.Rodrigues"
        )
    if np.linalg.det(rotation) < 0:
        raise InputError(f"{where}: rotation has det = -1 (a reflection); it must be a proper rotation")
    return pycolmap.Rigid3d(pycolmap.Rotation3d(rotation), translation)


def check_baseline(narrow_from_wide: pycolmap.Rigid3d, where: str) -> None:
    """The two cameras of a rig sit 1 mm - 5 m apart; outside, the translation is in other units than metres."""
    baseline = float(np.linalg.norm(narrow_from_wide.translation))
    low, high = BASELINE_RANGE_M
    if not low <= baseline <= high:
        hint = (f"in millimetres? {baseline:g} mm is {baseline / 1000:g} m" if baseline > high
                else "the two cameras cannot be at one point")
        raise InputError(f"{where} translation: the baseline |t| = {baseline:g} m is outside {low * 1000:g} mm - "
                         f"{high:g} m ({hint}); give the translation in metres")


def _sigma_vector(value, n: int, where: str) -> np.ndarray:
    try:
        out = np.array(value, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError, OverflowError) as e:
        raise InputError(f"{where}: expected {n} numbers, got {value!r}") from e
    if out.shape != (n,) or not np.isfinite(out).all() or (out < 0).any():
        raise InputError(f"{where}: expected {n} finite numbers >= 0, got {value!r}")
    return out


FOCAL_NAMES = ("f", "fx", "fy")
PRINCIPAL_NAMES = ("cx", "cy")


def check_camera_sigmas(sigmas: np.ndarray, camera: pycolmap.Camera, where: str) -> None:
    """The one check of a camera's sigmas (rigs.yaml's and the run's priors): each finite and >= 0; focal length
    and principal point ones > 0 (no calibration knows them exactly), the focal's at least 1e-4 px and at most
    10 % of the focal length, the principal point's at most 10 % of the image size; distortion terms may be 0
    (held fixed)."""
    names = [p.strip() for p in camera.params_info.split(",")]
    params = np.asarray(camera.params, dtype=np.float64)
    sizes = {"cx": camera.width, "cy": camera.height, "f": camera.width}
    for name, sigma, value in zip(names, np.asarray(sigmas, dtype=np.float64), params, strict=True):
        key = f"{where} ({name})"
        if not np.isfinite(sigma) or sigma < 0:
            raise InputError(f"{key}: must be a finite number >= 0, got {sigma}; recalibrate, or remove 'sigmas'")
        if name in FOCAL_NAMES and not MIN_SIGMA_FOCAL_PX <= sigma <= MAX_SIGMA_FOCAL * abs(value):
            raise InputError(f"{key}: the focal length's sigma {sigma:g} px must be at least {MIN_SIGMA_FOCAL_PX:g} px "
                             f"(no calibration knows it better) and at most {100 * MAX_SIGMA_FOCAL:g} % of {value:g} px; "
                             "recalibrate (pixels, 1 sigma), or remove 'sigmas'")
        if name in PRINCIPAL_NAMES and not MIN_SIGMA_FOCAL_PX <= sigma <= MAX_SIGMA_PRINCIPAL_POINT * sizes[name]:
            raise InputError(f"{key}: the principal point's sigma {sigma:g} px must be at least {MIN_SIGMA_FOCAL_PX:g} "
                             f"px and at most {100 * MAX_SIGMA_PRINCIPAL_POINT:g} % of the image size; recalibrate "
                             "(pixels, 1 sigma), or remove 'sigmas'")


def sigmas_from_entry(entry: dict, where: str, cameras: dict[str, pycolmap.Camera] | None = None) -> RigSigmas:
    """Read and check the uncertainty keys of one rig entry of rigs.yaml (absent keys stay None); ``cameras``: the
    entry's parsed cameras (parsed here when not given)."""
    out = RigSigmas()
    if cameras is None:
        cameras = {sensor: parse_camera(entry["sensors"][sensor], f"{where} sensor {sensor}") for sensor in SENSORS}
    for sensor in SENSORS:
        spec = entry["sensors"][sensor]
        if "sigmas" in spec:
            what = f"{where} sensor {sensor} sigmas (one per entry of params)"
            vector = _sigma_vector(spec["sigmas"], len(spec["params"]), what)
            check_camera_sigmas(vector, cameras[sensor], what)
            setattr(out, sensor, vector)
    pose = entry["narrow_from_wide"]
    if "sigma_rotation_deg" in pose:
        what = f"{where} narrow_from_wide sigma_rotation_deg"
        out.rotation_deg = _sigma_vector(pose["sigma_rotation_deg"], 3, what)
        if not ((out.rotation_deg >= MIN_SIGMA_ROTATION_DEG) & (out.rotation_deg <= MAX_SIGMA_ROTATION_DEG)).all():
            raise InputError(f"{what}: each must be {MIN_SIGMA_ROTATION_DEG:g} - {MAX_SIGMA_ROTATION_DEG:g} degrees, got "
                             f"{pose['sigma_rotation_deg']}; recalibrate, or remove the key")
    if "sigma_translation_m" in pose:
        what = f"{where} narrow_from_wide sigma_translation_m"
        out.translation_m = _sigma_vector(pose["sigma_translation_m"], 3, what)
        baseline = float(np.linalg.norm(np.asarray(pose["translation"], dtype=np.float64)))
        if not ((out.translation_m >= MIN_SIGMA_TRANSLATION_M) & (out.translation_m <= baseline)).all():
            raise InputError(f"{what}: each must be at least {MIN_SIGMA_TRANSLATION_M:g} m and below the baseline "
                             f"|t| = {baseline:g} m, got "
                             f"{pose['sigma_translation_m']}; recalibrate, or remove the key")
    if "covariance" in pose:
        what = f"{where} narrow_from_wide covariance"
        try:
            cov = np.array(pose["covariance"], dtype=np.float64)
        except (TypeError, ValueError, OverflowError) as e:
            raise InputError(f"{what}: expected a 6x6 matrix of numbers") from e
        if cov.shape != (6, 6) or not np.isfinite(cov).all():
            raise InputError(f"{what}: expected a finite 6x6 matrix, got shape {cov.shape}")
        scale = np.sqrt(np.clip(np.diag(cov), 1e-300, None))
        with np.errstate(over="ignore", invalid="ignore"):  # a variance of nothing under a large covariance: inf
            scaled = cov / np.outer(scale, scale)
        if ((np.diag(cov) < 0).any() or not (np.abs(cov - cov.T) <= 1e-6 * np.abs(cov.T)).all()
                or not np.isfinite(scaled).all() or np.linalg.eigvalsh(scaled).min() < -1e-6):
            raise InputError(f"{what}: must be symmetric positive semi-definite ([w (rad), t (m)])")
        if np.degrees(np.sqrt(np.diag(cov)[:3])).max() > MAX_SIGMA_ROTATION_DEG:
            raise InputError(f"{what}: a rotation variance above ({MAX_SIGMA_ROTATION_DEG:g} deg)^2; the rotation "
                             "block is in rad^2: recalibrate, or remove the key")
        out.covariance = cov
    return out


SIGNIFICANT = 4  # digits written for sigmas ...
COVARIANCE_SIGNIFICANT = 8  # ... and for the covariance (its eigenvalues then move by < 1e-7 relative)


def _round(values, digits: int = SIGNIFICANT) -> list[float]:
    return [float(f"{v:.{digits}g}") for v in np.ravel(values)]


def add_sigmas(entry: dict, sigmas: RigSigmas) -> dict:
    """Add the uncertainty keys to one rig's rigs.yaml entry (a dict as :func:`rigs_to_yaml` builds it)."""
    for sensor in SENSORS:
        if sigmas.sensor(sensor) is not None:
            entry["sensors"][sensor]["sigmas"] = _round(sigmas.sensor(sensor))
    pose = entry["narrow_from_wide"]
    if sigmas.rotation_deg is not None:
        pose["sigma_rotation_deg"] = _round(sigmas.rotation_deg)
    if sigmas.translation_m is not None:
        pose["sigma_translation_m"] = _round(sigmas.translation_m)
    if sigmas.covariance is not None:
        pose["covariance"] = [_round(row, COVARIANCE_SIGNIFICANT) for row in sigmas.covariance]
    return entry


def load_rigs(path: Path) -> list[RigCalibration]:
    """Read and validate rigs.yaml (or the same structure as JSON)."""
    path = Path(path)
    data = load_yaml_or_json(path, "rig calibration", max_bytes=MAX_RIGS_FILE_BYTES,
                             form="it starts 'units: meters' and 'rigs:', one entry per rig (README.md, Inputs)")
    check_keys(data, TOP_KEYS, str(path))
    units = data.get("units", "meters")
    if units not in ("meters", "metres", "m"):
        raise InputError(f"{path}: units must be meters (got {_short(units)}); convert translations to metres")
    entries = data.get("rigs")
    if not isinstance(entries, list) or not entries:
        raise InputError(f"{path}: expected a non-empty list under 'rigs'")
    if len(entries) > MAX_RIGS:
        raise InputError(f"{path}: {len(entries)} rigs, more than the {MAX_RIGS} any network has; is it the right "
                         "file?")
    rigs: list[RigCalibration] = []
    first_index: dict[str, int] = {}
    for index, entry in enumerate(entries):
        where = f"{path}: rigs[{index}]"
        if not isinstance(entry, dict) or entry.get("name") is None or entry.get("name") == "":
            raise InputError(f"{where}: every rig needs a 'name' (its folder name under IMAGES)")
        name = entry["name"]
        if not isinstance(name, str):
            kind = _KINDS.get(type(name).__name__, "no text")
            raise InputError(f"{where}: rig name {_short(name)} is read as {kind}, not text; quote it "
                             f"(name: \"{name}\") exactly as its folder under IMAGES is spelled")
        if "/" in name or "\\" in name or name.startswith(".") or "\0" in name:
            raise InputError(f"{where}: rig name {name!r} must be a plain folder name")
        if nfc(name) in first_index:
            raise InputError(f"{path}: rig names must be unique, repeated: '{name}' (rigs[{first_index[nfc(name)]}] and "
                             f"rigs[{index}])")
        first_index[nfc(name)] = index
        where = f"{path}: rig '{name}'"
        check_keys(entry, RIG_KEYS, where)
        sensors = entry.get("sensors")
        if isinstance(sensors, dict):
            check_keys(sensors, SENSORS, f"{where} sensors")
        if not isinstance(sensors, dict) or set(sensors) != set(SENSORS):
            raise InputError(f"{where}: 'sensors' must have exactly 'wide' and 'narrow'")
        wide = parse_camera(sensors["wide"], f"{where} sensor wide")
        narrow = parse_camera(sensors["narrow"], f"{where} sensor narrow")
        narrow_from_wide = parse_rigid3d(entry.get("narrow_from_wide"), f"{where} narrow_from_wide")
        check_baseline(narrow_from_wide, f"{where} narrow_from_wide")
        sigmas = sigmas_from_entry(entry, where, {"wide": wide, "narrow": narrow})
        rigs.append(RigCalibration(name=name, wide=wide, narrow=narrow, narrow_from_wide=narrow_from_wide,
                                   sigmas=None if sigmas.is_empty() else sigmas))
    return rigs


def rigs_to_yaml(rigs: Sequence[RigCalibration]) -> str:
    """rigs.yaml for ``rigs``, with their uncertainty keys where they have ``sigmas``."""
    entries = []
    for rig in rigs:
        entry = {
            "name": rig.name,
            "sensors": {"wide": camera_to_dict(rig.wide), "narrow": camera_to_dict(rig.narrow)},
            "narrow_from_wide": pose_to_dict(rig.narrow_from_wide, quaternion=False),
        }
        entries.append(add_sigmas(entry, rig.sigmas) if rig.sigmas is not None else entry)
    data = {"units": "meters", "rigs": entries}
    return yaml.safe_dump(data, sort_keys=False, default_flow_style=None, width=120)


def write_rigs(path: Path, rigs: Sequence[RigCalibration], *, overwrite: bool = False) -> Path:
    """Write rigs.yaml atomically; refuses to replace an existing file unless ``overwrite``."""
    return write_text_atomic(Path(path), rigs_to_yaml(rigs), overwrite=overwrite)


def add_posed_rig(reconstruction: pycolmap.Reconstruction, rig_id: int, calibration: RigCalibration,
                  rig_from_world: pycolmap.Rigid3d, frames: Sequence[dict[str, str]]) -> None:
    """Add one rig to ``reconstruction``: its wide (reference) and narrow cameras (ids ``2 rig_id - 1`` and
    ``2 rig_id``), the rig with E^sl, and one frame at ``rig_from_world`` per entry of ``frames`` (sensor ->
    image name). Frame and image ids continue after the largest ones already there."""
    sensors = {}
    for offset, sensor in enumerate(("wide", "narrow")):
        camera = copy.copy(calibration.camera(sensor))
        camera.camera_id = 2 * rig_id - 1 + offset
        reconstruction.add_camera(camera)
        sensors[sensor] = pycolmap.sensor_t(pycolmap.SensorType.CAMERA, camera.camera_id)
    rig = pycolmap.Rig(rig_id=rig_id)
    rig.add_ref_sensor(sensors["wide"])
    rig.add_sensor(sensors["narrow"], calibration.narrow_from_wide)
    reconstruction.add_rig(rig)
    frame_id, image_id = max(reconstruction.frames, default=0), max(reconstruction.images, default=0)
    for names in frames:
        frame_id += 1
        frame = pycolmap.Frame(frame_id=frame_id, rig_id=rig_id, rig_from_world=rig_from_world)
        images = []
        for sensor, name in names.items():
            image_id += 1
            images.append(pycolmap.Image(image_id=image_id, name=name, camera_id=sensors[sensor].id,
                                         frame_id=frame_id))
            frame.add_data_id(pycolmap.data_t(sensors[sensor], image_id))
        reconstruction.add_frame(frame)
        for image in images:
            reconstruction.add_image(image)
