"""Procedural shape families (chairs, cars): seeded, labelled, with materials and exact SDFs.

``generate(family, seed)`` draws the family's parameters with ``numpy.random.default_rng(seed)``
and returns a :class:`ProceduralObject`: the solid (mesh + signed distance, normalised to the
project's scale), per-part materials and the parameters themselves. Objects face +Z with +Y up.

Chair parameters (part labels: 0 seat, 1 legs, 2 back, 3 arms): seat width / depth / thickness /
height, leg count (3–4, or a central pedestal), leg shape (square / round), leg thickness, leg
splay, back height / tilt / thickness, back style (solid / slats, slat count), armrests.
Car parameters (0 body, 1 cabin, 2 wheels, 3 bumpers): body length / width / height, ground
clearance, cabin length / height / offset, wheel radius / width, axle count (2–3), bumpers.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Callable

import numpy as np

from ngp_mi.geometry.mesh import TriangleMesh
from ngp_mi.geometry.sdf import Box, Cylinder, Primitive, SolidShape, rotation


@dataclasses.dataclass(frozen=True)
class Material:
    """A part's appearance: linear-RGB diffuse albedo, specular (0–1) and roughness (0–1)."""

    albedo: tuple[float, float, float]
    specular: float = 0.5
    roughness: float = 0.5

    def to_mitsuba(self) -> dict[str, Any]:
        """A ``principled`` BSDF (the physically based "real" domain)."""
        return {"type": "principled", "base_color": {"type": "rgb", "value": list(self.albedo)},
                "specular": float(self.specular), "roughness": float(self.roughness)}

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)


@dataclasses.dataclass(frozen=True, eq=False)
class ProceduralObject:
    family: str
    seed: int
    params: dict[str, Any]
    solid: SolidShape
    materials: dict[int, Material]
    part_names: tuple[str, ...]

    @property
    def id(self) -> str:
        return f"{self.family}/{self.seed:06d}"

    def mesh(self) -> TriangleMesh:
        return self.solid.mesh()


def _leg(top: np.ndarray, length: float, outward: np.ndarray, splay_deg: float, thickness: float,
         round_leg: bool) -> Primitive:
    """A leg hanging from ``top``, leaning ``splay_deg`` towards ``outward`` (horizontal unit vector)."""
    s = math.radians(splay_deg)
    down = np.array([0.0, -math.cos(s), 0.0]) + math.sin(s) * outward
    center = top + down * length / 2
    axis = np.cross([0.0, -1.0, 0.0], down)
    R = rotation(axis, math.degrees(s)) if np.linalg.norm(axis) > 1e-9 else np.eye(3)
    if round_leg:
        return Cylinder(center, thickness / 2, length / 2, R)
    return Box(center, np.array([thickness / 2, length / 2, thickness / 2]), R)


def chair(rng: np.random.Generator) -> tuple[dict[str, Any], list[tuple[Primitive, int]]]:
    p = {
        "seat_width": rng.uniform(0.40, 0.60), "seat_depth": rng.uniform(0.38, 0.55),
        "seat_thickness": rng.uniform(0.03, 0.09), "seat_height": rng.uniform(0.38, 0.50),
        "legs": str(rng.choice(["3", "4", "4", "pedestal"])), "leg_shape": str(rng.choice(["square", "round"])),
        "leg_thickness": rng.uniform(0.03, 0.065), "leg_splay_deg": rng.uniform(0.0, 12.0),
        "back_height": rng.uniform(0.25, 0.55), "back_tilt_deg": rng.uniform(0.0, 20.0),
        "back_thickness": rng.uniform(0.02, 0.05), "back_style": str(rng.choice(["solid", "slats"])),
        "slat_count": int(rng.integers(2, 6)), "armrests": bool(rng.random() < 0.35),
    }
    w, d, t, h = p["seat_width"], p["seat_depth"], p["seat_thickness"], p["seat_height"]
    lt, bt = p["leg_thickness"], p["back_thickness"]
    parts: list[tuple[Primitive, int]] = [(Box(np.array([0.0, h - t / 2, 0.0]), np.array([w / 2, t / 2, d / 2])), 0)]

    under = h - t  # legs reach from the floor to the seat's underside
    round_leg = p["leg_shape"] == "round"
    if p["legs"] == "pedestal":
        parts.append((Cylinder(np.array([0.0, under / 2 + 0.02, 0.0]), lt, under / 2 - 0.02), 1))
        for k in range(5):
            a = 2 * math.pi * k / 5
            outward = np.array([math.sin(a), 0.0, math.cos(a)])
            parts.append((Box(np.array([0.0, 0.02, 0.0]) + outward * 0.14, np.array([lt / 2, 0.02, 0.14]),
                              rotation([0, 1, 0], math.degrees(a))), 1))
    else:
        inset = lt / 2 + 0.01
        corners = ([(-1, -1), (1, -1), (0, 1)] if p["legs"] == "3" else [(-1, -1), (1, -1), (-1, 1), (1, 1)])
        for sx, sz in corners:
            top = np.array([sx * (w / 2 - inset), under, sz * (d / 2 - inset)])
            outward = np.array([sx, 0.0, sz], dtype=np.float64)
            outward /= np.linalg.norm(outward)
            length = under / math.cos(math.radians(p["leg_splay_deg"]))
            parts.append((_leg(top, length, outward, p["leg_splay_deg"], lt, round_leg), 1))

    # The back rises from the seat's rear edge and leans backwards about the x axis.
    tilt = rotation([1, 0, 0], -p["back_tilt_deg"])
    base = np.array([0.0, h, -d / 2 + bt / 2])
    bh = p["back_height"]

    def back_box(local_center: np.ndarray, half: np.ndarray) -> Box:
        return Box(base + tilt @ local_center, half, tilt)

    if p["back_style"] == "solid":
        parts.append((back_box(np.array([0.0, bh / 2, 0.0]), np.array([w / 2, bh / 2, bt / 2])), 2))
    else:
        rail = 0.05
        parts.append((back_box(np.array([0.0, bh - rail / 2, 0.0]), np.array([w / 2, rail / 2, bt / 2])), 2))
        for sx in (-1, 1):
            parts.append((back_box(np.array([sx * (w / 2 - lt / 2), bh / 2, 0.0]), np.array([lt / 2, bh / 2, bt / 2])), 2))
        n = p["slat_count"]
        for k in range(n):
            x = (k + 1) / (n + 1) * (w - lt) - (w - lt) / 2
            parts.append((back_box(np.array([x, bh / 2, 0.0]), np.array([0.012, bh / 2, bt / 3])), 2))
    if p["armrests"]:
        arm_y = h + 0.2
        for sx in (-1, 1):
            x = sx * (w / 2 - 0.02)
            parts.append((Box(np.array([x, arm_y, 0.0]), np.array([0.025, 0.015, d / 2 - 0.02])), 3))
            parts.append((Box(np.array([x, (h + arm_y) / 2, d / 2 - 0.04]), np.array([0.015, (arm_y - h) / 2, 0.015])), 3))
    return p, parts


def car(rng: np.random.Generator) -> tuple[dict[str, Any], list[tuple[Primitive, int]]]:
    p = {
        "body_length": rng.uniform(0.9, 1.25), "body_width": rng.uniform(0.38, 0.52),
        "body_height": rng.uniform(0.13, 0.24), "clearance": rng.uniform(0.03, 0.09),
        "cabin_length": rng.uniform(0.35, 0.6), "cabin_height": rng.uniform(0.10, 0.22),
        "cabin_offset": rng.uniform(-0.15, 0.12), "wheel_radius": rng.uniform(0.08, 0.14),
        "wheel_width": rng.uniform(0.05, 0.09), "axles": int(rng.choice([2, 2, 2, 3])),
        "bumpers": bool(rng.random() < 0.6),
    }
    L, W, H, c = p["body_length"], p["body_width"], p["body_height"], p["clearance"]
    r = p["wheel_radius"]
    body_y = c + r * 0.6 + H / 2
    parts: list[tuple[Primitive, int]] = [(Box(np.array([0.0, body_y, 0.0]), np.array([W / 2, H / 2, L / 2])), 0)]
    cabin_l = p["cabin_length"] * L
    cabin_z = p["cabin_offset"] * L
    parts.append((Box(np.array([0.0, body_y + H / 2 + p["cabin_height"] / 2, cabin_z]),
                      np.array([W / 2 * 0.85, p["cabin_height"] / 2, cabin_l / 2])), 1))
    axle_z = np.linspace(-L / 2 + 1.3 * r, L / 2 - 1.3 * r, p["axles"])
    wheel_R = rotation([0, 0, 1], 90.0)  # cylinder axis along x
    for z in axle_z:
        for sx in (-1, 1):
            centre = np.array([sx * (W / 2 - p["wheel_width"] / 2 + 0.01), r, z])
            parts.append((Cylinder(centre, r, p["wheel_width"] / 2, wheel_R), 2))
    if p["bumpers"]:
        for sz in (-1, 1):
            parts.append((Box(np.array([0.0, body_y - H / 4, sz * (L / 2 + 0.02)]), np.array([W / 2, 0.03, 0.025])), 3))
    return p, parts


def _chair_materials(rng: np.random.Generator) -> dict[int, Material]:
    woods = np.array([[0.40, 0.22, 0.10], [0.55, 0.35, 0.18], [0.25, 0.13, 0.06], [0.70, 0.55, 0.35]])
    fabrics = np.array([[0.60, 0.10, 0.08], [0.10, 0.25, 0.55], [0.15, 0.40, 0.15], [0.75, 0.72, 0.65], [0.08, 0.08, 0.08]])

    def jitter(rgb: np.ndarray) -> tuple[float, float, float]:
        return tuple(float(x) for x in np.clip(rgb * rng.uniform(0.8, 1.2, 3), 0.02, 0.95))  # type: ignore[return-value]

    frame = Material(jitter(woods[rng.integers(len(woods))]), specular=0.3, roughness=float(rng.uniform(0.4, 0.8)))
    cover = Material(jitter(fabrics[rng.integers(len(fabrics))]), specular=0.2, roughness=float(rng.uniform(0.6, 0.95)))
    back = cover if rng.random() < 0.7 else frame
    return {0: cover, 1: frame, 2: back, 3: frame}


def _car_materials(rng: np.random.Generator) -> dict[int, Material]:
    hue = rng.uniform(0, 1)
    paint = np.clip(np.array([abs(math.sin(math.pi * (hue + k / 3))) for k in range(3)]) ** 2 * 0.8, 0.02, 0.9)
    return {0: Material(tuple(float(x) for x in paint), specular=0.8, roughness=float(rng.uniform(0.1, 0.35))),
            1: Material((0.03, 0.04, 0.05), specular=0.9, roughness=0.05),
            2: Material((0.03, 0.03, 0.03), specular=0.2, roughness=0.9),
            3: Material((0.5, 0.5, 0.52), specular=0.7, roughness=0.25)}


@dataclasses.dataclass(frozen=True)
class Family:
    build: Callable[[np.random.Generator], tuple[dict[str, Any], list[tuple[Primitive, int]]]]
    materials: Callable[[np.random.Generator], dict[int, Material]]
    part_names: tuple[str, ...]


FAMILIES: dict[str, Family] = {
    "chair": Family(chair, _chair_materials, ("seat", "legs", "back", "arms")),
    "car": Family(car, _car_materials, ("body", "cabin", "wheels", "bumpers")),
}


def generate(family: str, seed: int) -> ProceduralObject:
    """The object number ``seed`` of ``family``: same seed, same object."""
    if family not in FAMILIES:
        raise ValueError(f"unknown shape family {family!r}; choose one of {sorted(FAMILIES)}")
    spec = FAMILIES[family]
    rng = np.random.default_rng([seed, sum(map(ord, family))])
    params, parts = spec.build(rng)
    solid = SolidShape(tuple(parts), name=f"{family}_{seed:06d}").normalized()
    params = {k: (round(float(v), 6) if isinstance(v, float) else v) for k, v in params.items()}
    return ProceduralObject(family, seed, params, solid, spec.materials(rng), spec.part_names)
