"""Light sources: directional and point lights, the paper's overhead training rig, JSON and Mitsuba.

Radiometry (linear RGB, per channel):

* :class:`DirectionalLight` — ``direction`` is the unit vector *towards* the light (world space);
  ``irradiance`` E is the power per unit area arriving on a surface facing the light.
  A Lambertian surface of albedo ρ at angle θ to it has radiance ``ρ E cos θ / π``.
* :class:`PointLight` — ``position`` in world space; ``intensity`` I (power per steradian), so the
  irradiance at distance r and angle θ is ``I cos θ / r²``.

The Blinn-Phong renderer of the paper (App. A) has no 1/π: ``I = Σ_l E_l k_d max(N·L, 0) I_d + …``.
The same :class:`DirectionalLight` therefore gives a Blinn-Phong diffuse value π times the
physically based radiance; comparison code divides by π (see ``ngp_mi.render``).
"""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path
from typing import Any, Iterable, Sequence, Union

import numpy as np

from ngp_mi.atomic import write_text

Vec3 = tuple[float, float, float]


def _vec3(value: Any, field: str) -> Vec3:
    try:
        array = np.asarray(value, dtype=np.float64).reshape(-1)
    except (TypeError, ValueError):
        raise ValueError(f"light {field} must be 3 numbers, got {value!r}") from None
    if array.shape != (3,):
        raise ValueError(f"light {field} must be 3 numbers, got {value!r}")
    if not np.all(np.isfinite(array)):
        raise ValueError(f"light {field} must be finite, got {array.tolist()}")
    return tuple(float(x) for x in array)  # type: ignore[return-value]


def _rgb(value: Any, field: str) -> Vec3:
    """A non-negative, finite RGB triple; a single number means grey."""
    if np.isscalar(value):
        value = (value, value, value)
    rgb = _vec3(value, field)
    if min(rgb) < 0:
        raise ValueError(f"light {field} must be non-negative, got {list(rgb)}")
    return rgb


@dataclasses.dataclass(frozen=True)
class DirectionalLight:
    """A light at infinity: unit ``direction`` towards the light, RGB ``irradiance``."""

    direction: Vec3
    irradiance: Vec3 = (1.0, 1.0, 1.0)

    def __post_init__(self) -> None:
        d = np.asarray(_vec3(self.direction, "direction"))
        norm = float(np.linalg.norm(d))
        if norm < 1e-12:
            raise ValueError(f"light direction must be non-zero, got {d.tolist()}")
        object.__setattr__(self, "direction", tuple(float(x) for x in d / norm))
        object.__setattr__(self, "irradiance", _rgb(self.irradiance, "irradiance"))

    def to_dict(self) -> dict[str, Any]:
        return {"type": "directional", "direction": list(self.direction), "irradiance": list(self.irradiance)}

    def to_mitsuba(self) -> dict[str, Any]:
        """Mitsuba ``directional`` emitter; Mitsuba's direction is the one light *travels*."""
        return {"type": "directional", "direction": [-x for x in self.direction],
                "irradiance": {"type": "rgb", "value": list(self.irradiance)}}


@dataclasses.dataclass(frozen=True)
class PointLight:
    """An isotropic point light at ``position`` with RGB radiant ``intensity``."""

    position: Vec3
    intensity: Vec3 = (1.0, 1.0, 1.0)

    def __post_init__(self) -> None:
        object.__setattr__(self, "position", _vec3(self.position, "position"))
        object.__setattr__(self, "intensity", _rgb(self.intensity, "intensity"))

    def to_dict(self) -> dict[str, Any]:
        return {"type": "point", "position": list(self.position), "intensity": list(self.intensity)}

    def to_mitsuba(self) -> dict[str, Any]:
        return {"type": "point", "position": list(self.position),
                "intensity": {"type": "rgb", "value": list(self.intensity)}}


Light = Union[DirectionalLight, PointLight]
_LIGHT_TYPES = {"directional": DirectionalLight, "point": PointLight}


def overhead_rig(count: int = 4, elevation_deg: float = 50.0, irradiance: float | Sequence[float] = 0.5,
                 azimuth_offset_deg: float = 45.0) -> list[DirectionalLight]:
    """The paper's training lights: ``count`` white directional lights placed uniformly overhead.

    The paper says only "uniformly 4 overhead white directional lights"; we place them at
    azimuths ``offset + k·360°/count`` (from +Z towards +X) and a common elevation above the
    horizon, so that every side of an object facing the camera range gets light.
    """
    if count < 1:
        raise ValueError(f"overhead rig needs count >= 1, got {count}")
    if not 0.0 < elevation_deg <= 90.0:
        raise ValueError(f"overhead rig elevation must lie in (0, 90] degrees, got {elevation_deg}")
    el = math.radians(elevation_deg)
    lights = []
    for k in range(count):
        az = math.radians(azimuth_offset_deg + 360.0 * k / count)
        direction = (math.cos(el) * math.sin(az), math.sin(el), math.cos(el) * math.cos(az))
        lights.append(DirectionalLight(direction, irradiance))  # type: ignore[arg-type]
    return lights


def light_from_dict(data: dict[str, Any], where: str = "light") -> Light:
    """Parse one light; errors name ``where`` and the offending field."""
    if not isinstance(data, dict):
        raise ValueError(f"{where}: expected an object, got {type(data).__name__}")
    kind = data.get("type")
    if kind not in _LIGHT_TYPES:
        raise ValueError(f"{where}: field 'type' must be one of {sorted(_LIGHT_TYPES)}, got {kind!r}")
    cls = _LIGHT_TYPES[kind]
    fields = {f.name for f in dataclasses.fields(cls)}
    unknown = set(data) - fields - {"type"}
    if unknown:
        raise ValueError(f"{where}: unknown field(s) {sorted(unknown)} for a {kind} light (expected {sorted(fields)})")
    try:
        return cls(**{k: v for k, v in data.items() if k != "type"})
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{where}: {exc}") from None


def lights_to_json(lights: Iterable[Light]) -> str:
    return json.dumps({"lights": [light.to_dict() for light in lights]}, indent=2)


def lights_from_json(text: str, where: str = "lights") -> list[Light]:
    """Parse ``{"lights": [...]}`` (or a bare list) into lights."""
    try:
        data = json.loads(text)
    except json.JSONDecodeError as exc:
        raise ValueError(f"{where}: not valid JSON ({exc})") from None
    items = data.get("lights") if isinstance(data, dict) else data
    if not isinstance(items, list):
        raise ValueError(f"{where}: expected a list under 'lights'")
    return [light_from_dict(item, f"{where}[{i}]") for i, item in enumerate(items)]


def save_lights(path: str | Path, lights: Iterable[Light]) -> None:
    write_text(path, lights_to_json(lights) + "\n")


def load_lights(path: str | Path) -> list[Light]:
    path = Path(path)
    try:
        text = path.read_text()
    except OSError as exc:
        raise ValueError(f"{path}: cannot read light file ({exc.strerror})") from None
    return lights_from_json(text, where=str(path))


def lights_to_mitsuba(lights: Iterable[Light]) -> dict[str, dict[str, Any]]:
    """Scene-dictionary entries ``{"light_0": {...}, ...}`` for ``mi.load_dict``."""
    return {f"light_{i}": light.to_mitsuba() for i, light in enumerate(lights)}
