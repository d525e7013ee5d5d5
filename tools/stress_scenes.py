"""Generated stress scenes for quality decisions: kinds of content that the shared captures have little
of, made deterministically (seeded) so that anyone can rebuild them; nothing is committed as data.

    python tools/stress_scenes.py OUT_DIR [--scale 1.0]

Writes eight INRIA 3DGS PLY files (SH degree 1, sizes and opacities in the ranges of trained scenes:
log-scales about -7 to -2, opacities from faint to opaque; the unbounded scene's distant splats up
to about one unit, as trainers make a capture's far background):

- ``stress_fur.ply``: thin, overlapping, semi-transparent strands standing on a sphere (fur, hair).
- ``stress_grass.ply``: a field of thin blades with flowers on a ground of flat splats.
- ``stress_panels.ply``: flat-coloured opaque panels meeting at sharp edges (signs, walls, boxes).
- ``stress_backdrop.ply``: a small opaque object in front of a few large, faint background splats.
- ``stress_unbounded.ply``: an outdoor capture's layout: a textured ground out to the horizon (its
  splats fewer and larger with distance), a far shell of large opaque splats (sky and a tree line)
  and a detailed centre (a striped ball and a semi-transparent bush). Up is -y, as ``eval``'s
  default; ``eval``'s orbit lies between the ground's edge and the shell.
- ``stress_texture.ply``: printed and patterned surfaces (a picture with lettering on a wall, a rug, a
  labelled can), their splats as a trainer leaves them: sizes spread about the spacing, stretched
  and layered, a third of them faint.
- ``stress_glossy.ply``: shiny objects (a ball, a torus, a box) whose highlight moves with the view:
  degree-1 SH terms as large as 0.45 in colour.
- ``stress_wires.ply``: thin structures in front of a patterned wall: a picket fence with posts and
  rails, sagging cables and a spoked wheel, each wire a run of needles along it with a faint halo,
  as a trainer leaves them (radii 0.0025 to 0.02, the wall 2.6 wide).

``--scale`` multiplies every splat count (1.0: 55k to 120k splats a scene). The first four scenes
are those of the measurements in docs/quality.md before the fifth was added, the first five those
before the texture and glossy kinds were, the first seven those before the wires were.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

SH_DEGREE = 1
SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199  # the degree-1 real SH basis' factor
R_GROUND = 3.0  # the unbounded scene's ground radius; its far shell lies at 12 to 18


def _quat_from_axes(x: np.ndarray, z: np.ndarray) -> np.ndarray:
    """Unit quaternions (w, x, y, z) of the rotations whose columns are x, z x x, z (rows of unit
    vectors, x orthogonal to z)."""
    y = np.cross(z, x)
    r = np.stack([x, y, z], axis=2)  # columns
    w = np.sqrt(np.clip(1.0 + r[:, 0, 0] + r[:, 1, 1] + r[:, 2, 2], 1e-12, None)) / 2.0
    q = np.stack([w, (r[:, 2, 1] - r[:, 1, 2]) / (4 * w), (r[:, 0, 2] - r[:, 2, 0]) / (4 * w), (r[:, 1, 0] - r[:, 0, 1]) / (4 * w)], 1)
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def _orthonormal(z: np.ndarray, rng) -> tuple[np.ndarray, np.ndarray]:
    """Unit z and a random unit x orthogonal to it, per row."""
    z = z / np.linalg.norm(z, axis=1, keepdims=True)
    a = rng.normal(size=z.shape)
    x = a - (a * z).sum(1, keepdims=True) * z
    return x / np.linalg.norm(x, axis=1, keepdims=True), z


def _splats(means, z_axes, log_scales, opacity, rgb, rng, sh_noise=0.05) -> dict[str, np.ndarray]:
    """Arrays for splats whose third scale axis is ``z_axes``; rgb in [0, 1] becomes the SH DC term,
    the degree-1 terms are small noise (mild view dependence)."""
    n = len(means)
    x, z = _orthonormal(z_axes, rng)
    rest = rng.normal(scale=sh_noise, size=(n, 3 * ((SH_DEGREE + 1) ** 2 - 1)))
    return {
        "means": means.astype(np.float32),
        "rotations": _quat_from_axes(x, z).astype(np.float32),
        "log_scales": log_scales.astype(np.float32),
        "opacities": np.log(opacity / (1.0 - opacity)).astype(np.float32),
        "features": np.concatenate([(rgb - 0.5) / SH_C0, rest], 1).astype(np.float32),
    }


def _concat(parts: list[dict]) -> dict[str, np.ndarray]:
    return {key: np.concatenate([p[key] for p in parts]) for key in parts[0]}


def fur(rng, scale: float) -> dict[str, np.ndarray]:
    """Strands on a unit sphere: each strand a chain of thin elongated splats along a bent path."""
    strands, per = int(4000 * scale), 20
    roots = rng.normal(size=(strands, 3))
    roots /= np.linalg.norm(roots, axis=1, keepdims=True)
    bend = rng.normal(scale=0.3, size=(strands, 3))
    t = np.linspace(0.0, 1.0, per)
    length = rng.uniform(0.15, 0.3, strands)[:, None, None]
    path = roots[:, None, :] * (1.0 + length * t[None, :, None]) + bend[:, None, :] * (length * t[None, :, None]) ** 2
    tangent = np.gradient(path, axis=1).reshape(-1, 3)
    means = path.reshape(-1, 3)
    n = len(means)
    seg = (length[:, 0, 0] / per).repeat(per)
    log_scales = np.stack([np.log(0.8 * seg), np.full(n, np.log(0.002)), np.full(n, np.log(0.002))], 1)
    x = tangent / np.linalg.norm(tangent, axis=1, keepdims=True)  # the long axis along the strand
    z = np.cross(x, rng.normal(size=(n, 3)))
    base = rng.uniform(0.55, 0.85, (strands, 1)) * np.array([1.0, 0.8, 0.55])
    rgb = np.clip(base.repeat(per, 0) * (0.7 + 0.3 * np.tile(t, strands))[:, None], 0, 1)
    opacity = rng.uniform(0.15, 0.6, n)
    out = _splats(means, z, log_scales, opacity, rgb, rng)
    # the splat frame's first axis is random in the plane orthogonal to z: put the long scale on it
    xs, _ = _orthonormal(z, rng)
    along = np.abs((xs * x).sum(1)) > np.abs((np.cross(z / np.linalg.norm(z, axis=1, keepdims=True), xs) * x).sum(1))
    out["log_scales"][~along] = out["log_scales"][~along][:, [1, 0, 2]]
    skin = _sphere_shell(rng, int(8000 * scale), 1.0, np.array([0.45, 0.35, 0.25]))
    return _concat([out, skin])


def _sphere_shell(rng, n: int, radius: float, rgb) -> dict[str, np.ndarray]:
    normals = rng.normal(size=(n, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    s = radius * np.sqrt(4 * np.pi / n)
    log_scales = np.stack([np.full(n, np.log(s)), np.full(n, np.log(s)), np.full(n, np.log(s * 0.05))], 1)
    colour = np.clip(np.asarray(rgb) + rng.normal(scale=0.03, size=(n, 3)), 0, 1)
    return _splats(normals * radius, normals, log_scales, rng.uniform(0.9, 0.99, n), colour, rng)


def grass(rng, scale: float) -> dict[str, np.ndarray]:
    """Blades (vertical chains of thin splats) on a flat ground, with a few flower heads."""
    blades, per = int(3000 * scale), 12
    roots = np.concatenate([rng.uniform(-1, 1, (blades, 2)), np.zeros((blades, 1))], 1)
    lean = rng.normal(scale=0.15, size=(blades, 3)) * np.array([1, 1, 0])
    t = np.linspace(0, 1, per)
    height = rng.uniform(0.1, 0.35, blades)[:, None, None]
    path = roots[:, None, :] + (np.array([0, 0, 1.0]) + lean[:, None, :] * t[None, :, None]) * height * t[None, :, None]
    means = path.reshape(-1, 3)
    n = len(means)
    seg = (height[:, 0, 0] / per).repeat(per)
    width = 0.006 * (1.0 - 0.8 * np.tile(t, blades))
    face = np.cross(np.array([0, 0, 1.0]), rng.normal(size=(blades, 3))).repeat(per, 0)
    log_scales = np.stack([np.log(width), np.log(0.7 * seg), np.full(n, np.log(0.0005))], 1)
    green = rng.uniform(0.25, 0.6, (blades, 1)) * np.array([0.5, 1.0, 0.3])
    rgb = np.clip(green.repeat(per, 0) * (0.6 + 0.4 * np.tile(t, blades))[:, None], 0, 1)
    out = _splats(means, face, log_scales, rng.uniform(0.6, 0.95, n), rgb, rng)
    flowers = int(300 * scale)
    tips = path[rng.choice(blades, flowers, replace=False), -1]
    petals = tips.repeat(6, 0) + rng.normal(scale=0.006, size=(flowers * 6, 3))
    petal_rgb = np.array([[0.95, 0.85, 0.2], [0.9, 0.3, 0.5], [0.95, 0.95, 0.95]])[rng.integers(0, 3, flowers)].repeat(6, 0)
    fl = _splats(petals, rng.normal(size=(flowers * 6, 3)), np.log(np.full((flowers * 6, 3), [0.006, 0.006, 0.001])),
                 np.full(flowers * 6, 0.9), petal_rgb, rng)
    n_ground = int(20000 * scale)
    ground_xy = rng.uniform(-1.1, 1.1, (n_ground, 2))
    s = 2.2 / np.sqrt(n_ground)
    gr = _splats(np.concatenate([ground_xy, np.zeros((n_ground, 1))], 1), np.tile([0, 0, 1.0], (n_ground, 1)),
                 np.log(np.tile([s, s, s * 0.05], (n_ground, 1))), rng.uniform(0.85, 0.99, n_ground),
                 np.clip(np.array([0.35, 0.27, 0.18]) + rng.normal(scale=0.04, size=(n_ground, 3)), 0, 1), rng)
    return _concat([out, fl, gr])


def panels(rng, scale: float) -> dict[str, np.ndarray]:
    """Axis-aligned opaque panels of flat, distinct colours meeting at right angles: each panel a
    jittered grid of flat splats, so the edges between colours are sharp."""
    parts = []
    colours = np.array([[0.9, 0.1, 0.1], [0.1, 0.6, 0.9], [0.95, 0.95, 0.9], [0.1, 0.1, 0.12], [0.95, 0.8, 0.1], [0.2, 0.7, 0.3]])
    per = int(12000 * scale)
    for k in range(8):
        axis = k % 3
        origin = rng.uniform(-0.8, 0.8, 3)
        uv = rng.uniform(-0.5, 0.5, (per, 2))
        means = np.repeat(origin[None], per, 0)
        others = [a for a in range(3) if a != axis]
        means[:, others[0]] += uv[:, 0]
        means[:, others[1]] += uv[:, 1]
        normal = np.zeros((per, 3))
        normal[:, axis] = 1.0
        s = 1.0 / np.sqrt(per) * 0.8
        # two colours per panel, split by a sharp diagonal edge
        side = (uv[:, 0] + 0.3 * uv[:, 1]) > 0
        rgb = np.where(side[:, None], colours[k % 6], colours[(k + 2) % 6])
        parts.append(_splats(means, normal, np.log(np.tile([s, s, s * 0.02], (per, 1))), np.full(per, 0.99), rgb, rng, 0.01))
    return _concat(parts)


def backdrop(rng, scale: float) -> dict[str, np.ndarray]:
    """An opaque textured object in front of a few large faint splats (sky, haze)."""
    obj = _sphere_shell(rng, int(60000 * scale), 0.4, np.array([0.6, 0.5, 0.4]))
    checker = ((np.floor(obj["means"][:, 0] * 20) + np.floor(obj["means"][:, 1] * 20)) % 2).astype(bool)
    obj["features"][checker, :3] = (np.array([0.2, 0.25, 0.6]) - 0.5) / SH_C0
    m = int(200 * scale) + 8
    far = rng.normal(size=(m, 3))
    far = far / np.linalg.norm(far, axis=1, keepdims=True) * rng.uniform(2.0, 4.0, (m, 1))
    back = _splats(far, rng.normal(size=(m, 3)), np.log(rng.uniform(0.3, 1.2, (m, 3))), rng.uniform(0.02, 0.15, m),
                   np.clip(np.array([0.55, 0.65, 0.85]) + rng.normal(scale=0.05, size=(m, 3)), 0, 1), rng)
    return _concat([obj, back])


def unbounded(rng, scale: float) -> dict[str, np.ndarray]:
    """An outdoor capture's layout, up -y: a ground whose splats grow and thin out with distance (the
    density of centres falls as 1/r out to R_GROUND), textured at every distance; a far shell of
    large opaque splats (sky, a tree line at the horizon, ground colour below it); at the centre a
    striped ball resting on the ground and a semi-transparent bush."""
    ball = _sphere_shell(rng, int(20000 * scale), 0.3, np.array([0.7, 0.3, 0.2]))
    ball["means"][:, 1] -= 0.3  # resting on the ground (y = 0, up -y)
    stripes = (np.floor(ball["means"][:, 1] * 25) % 2).astype(bool)
    ball["features"][stripes, :3] = (np.array([0.9, 0.85, 0.7]) - 0.5) / SH_C0
    n_bush = int(15000 * scale)
    clumps = rng.normal(scale=0.15, size=(40, 3)) + np.array([0.7, -0.3, 0.2])
    leaves = clumps[rng.integers(0, 40, n_bush)] + rng.normal(scale=0.05, size=(n_bush, 3))
    green = rng.uniform(0.15, 0.45, (n_bush, 1)) * np.array([0.45, 1.0, 0.35])
    bush = _splats(leaves, rng.normal(size=(n_bush, 3)), np.log(rng.uniform(0.004, 0.012, (n_bush, 3)) * [1, 1, 0.2]),
                   rng.uniform(0.3, 0.9, n_bush), np.clip(green, 0, 1), rng)
    n_ground = int(50000 * scale)
    r = np.exp(rng.uniform(np.log(0.05), np.log(R_GROUND), n_ground))
    angle = rng.uniform(0, 2 * np.pi, n_ground)
    xz = np.stack([r * np.cos(angle), r * np.sin(angle)], 1)
    ground_size = 0.02 * r + 0.004
    cell = np.floor(xz / (0.15 * np.maximum(r, 0.3))[:, None]).astype(np.int64)  # patches that grow with r
    patch = ((cell[:, 0] * 73856093) ^ (cell[:, 1] * 19349663)) % 997 / 997.0
    soil = np.where((patch > 0.6)[:, None], [0.3, 0.45, 0.15], [0.45, 0.35, 0.22]) + rng.normal(scale=0.04, size=(n_ground, 3))
    ground = _splats(np.stack([xz[:, 0], np.zeros(n_ground), xz[:, 1]], 1), np.tile([0, 1.0, 0], (n_ground, 1)),
                     np.log(np.stack([ground_size, ground_size, ground_size * 0.1], 1)), rng.uniform(0.8, 0.99, n_ground), np.clip(soil, 0, 1), rng)
    n_far = int(6000 * scale)
    d = rng.normal(size=(n_far, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    elevation = -d[:, 1]
    distance = rng.uniform(12.0, 18.0, n_far)
    far_size = distance * np.sqrt(4 * np.pi / n_far) * 0.9
    sky = np.array([0.45, 0.6, 0.9]) + np.clip(elevation, 0, 1)[:, None] * np.array([0.1, 0.09, 0.02])
    treeline = (elevation > -0.05) & (elevation < 0.12 + 0.06 * np.sin(7 * np.arctan2(d[:, 2], d[:, 0])))
    colour = np.where(treeline[:, None], np.array([0.12, 0.22, 0.1]) + rng.normal(scale=0.05, size=(n_far, 3)), sky)
    colour = np.where((elevation <= -0.05)[:, None], [0.4, 0.33, 0.22], colour)
    far = _splats(d * distance[:, None], d, np.log(np.stack([far_size, far_size, far_size * 0.3], 1)), rng.uniform(0.85, 0.99, n_far),
                  np.clip(colour, 0, 1), rng)
    return _concat([ball, bush, ground, far])


def _value_noise(u: np.ndarray, v: np.ndarray, freq: float, seed: int) -> np.ndarray:
    """Smooth value noise in [0, 1] at (u, v): random values on a grid of ``freq`` cells a unit
    (hashed from the cell and ``seed``), blended with smoothstep weights."""
    x, y = u * freq, v * freq
    x0, y0 = np.floor(x).astype(np.int64), np.floor(y).astype(np.int64)
    fx, fy = x - x0, y - y0
    fx, fy = fx * fx * (3 - 2 * fx), fy * fy * (3 - 2 * fy)

    def cell(i, j):
        k = (i * 73856093) ^ (j * 19349663) ^ (seed * 83492791)
        k = (k ^ (k >> 13)) * 1274126177
        return ((k ^ (k >> 16)) & 0xFFFF) / 65535.0

    a, b, c, d = cell(x0, y0), cell(x0 + 1, y0), cell(x0, y0 + 1), cell(x0 + 1, y0 + 1)
    return (a * (1 - fx) + b * fx) * (1 - fy) + (c * (1 - fx) + d * fx) * fy


def _printed(u: np.ndarray, v: np.ndarray, seed: int, palette: np.ndarray) -> np.ndarray:
    """The colour of a printed picture at surface coordinates (u, v) in [0, 1]^2: regions of the
    palette's colours from four octaves of value noise, rows of thin dark bars like lettering, and
    a sharp-edged frame."""
    octaves = [3, 7, 17, 41]
    t = sum(_value_noise(u, v, f, seed + o) / (o + 1) for o, f in enumerate(octaves)) / sum(1 / (o + 1) for o in range(len(octaves)))
    index = np.clip((t * len(palette)).astype(int), 0, len(palette) - 1)
    rgb = palette[index] * (0.85 + 0.3 * (t * len(palette) - index))[:, None]
    row = np.floor(v * 24)
    lettering = ((v * 24 - row) < 0.35) & (row % 3 == 1) & (_value_noise(u * 3.0, row / 24.0, 9, seed + 9) > 0.5)
    rgb = np.where(lettering[:, None], [0.08, 0.07, 0.06], rgb)
    frame = (u < 0.04) | (u > 0.96) | (v < 0.04) | (v > 0.96)
    return np.clip(np.where(frame[:, None], [0.55, 0.4, 0.15], rgb), 0, 1)


def _trained_surface(rng, means, normals, spacing: float, rgb) -> dict[str, np.ndarray]:
    """Splats on a surface as a trainer leaves them: sizes log-normal about the centres' spacing,
    stretched up to 3:1 in the surface at random, thin along the normal, a few layers deep; about a
    third of them faint (opacity 0.05 to 0.5), the rest nearly opaque."""
    n = len(means)
    means = means + normals * rng.normal(scale=0.15 * spacing, size=(n, 1))
    size = spacing * np.exp(rng.normal(scale=0.45, size=n))
    stretch = np.exp(rng.uniform(0, np.log(3.0), n))
    log_scales = np.log(np.stack([size * np.sqrt(stretch), size / np.sqrt(stretch), 0.05 * size], 1))
    opacity = np.where(rng.random(n) < 0.35, rng.uniform(0.05, 0.5, n), rng.uniform(0.75, 0.99, n))
    return _splats(means, normals, log_scales, opacity, np.clip(rgb + rng.normal(scale=0.03, size=rgb.shape), 0, 1), rng)


def texture(rng, scale: float) -> dict[str, np.ndarray]:
    """Printed and patterned surfaces: a picture on a wall, a rug on the floor and a labelled can
    standing on it (up -y), each a ``_trained_surface`` coloured by ``_printed``."""
    palettes = [
        np.array([[0.8, 0.2, 0.15], [0.95, 0.85, 0.6], [0.2, 0.35, 0.6], [0.3, 0.55, 0.3], [0.9, 0.6, 0.2]]),
        np.array([[0.55, 0.1, 0.12], [0.85, 0.75, 0.55], [0.15, 0.2, 0.35], [0.7, 0.45, 0.25]]),
        np.array([[0.95, 0.95, 0.92], [0.85, 0.1, 0.1], [0.1, 0.1, 0.1], [0.95, 0.8, 0.1]]),
    ]
    n = int(45000 * scale)  # the picture: z = -0.5, x in [-1, 1], y in [-0.7, 0.7]
    uv = rng.random((n, 2))
    means = np.stack([uv[:, 0] * 2 - 1, uv[:, 1] * 1.4 - 0.7, np.full(n, -0.5)], 1)
    picture = _trained_surface(rng, means, np.tile([0, 0, 1.0], (n, 1)), np.sqrt(2.8 / n), _printed(uv[:, 0], uv[:, 1], 1, palettes[0]))
    n = int(35000 * scale)  # the rug: y = 0.6
    uv = rng.random((n, 2))
    means = np.stack([uv[:, 0] * 1.6 - 0.8, np.full(n, 0.6), uv[:, 1] * 1.2 - 0.4], 1)
    rug = _trained_surface(rng, means, np.tile([0, 1.0, 0], (n, 1)), np.sqrt(1.92 / n), _printed(uv[:, 0], uv[:, 1], 2, palettes[1]))
    n = int(20000 * scale)  # the can: radius 0.2, height 0.5
    uv = rng.random((n, 2))
    angle = uv[:, 0] * 2 * np.pi
    normals = np.stack([np.cos(angle), np.zeros(n), np.sin(angle)], 1)
    means = np.stack([0.2 * np.cos(angle) + 0.3, 0.6 - uv[:, 1] * 0.5, 0.2 * np.sin(angle) + 0.1], 1)
    can = _trained_surface(rng, means, normals, np.sqrt(2 * np.pi * 0.2 * 0.5 / n), _printed(uv[:, 0], uv[:, 1], 3, palettes[2]))
    return _concat([picture, rug, can])


def _shiny(rng, means, normals, spacing: float, base) -> dict[str, np.ndarray]:
    """A ``_trained_surface`` of one base colour whose degree-1 SH terms add a white highlight that
    follows the view: strength (d . l) for a fixed direction l, strength 0.25 to 0.45 times how far
    the surface faces l (the degree-1 basis in the INRIA order is (-C1 y, C1 z, -C1 x))."""
    n = len(means)
    out = _trained_surface(rng, means, normals, spacing, np.tile(base, (n, 1)))
    light = np.array([0.5, -0.7, 0.5]) / np.linalg.norm([0.5, -0.7, 0.5])
    strength = rng.uniform(0.25, 0.45, n) * np.clip(normals @ light + 0.3, 0, None)
    coefficients = np.array([-light[1], light[2], -light[0]]) / SH_C1
    rest = out["features"][:, 3:].reshape(n, 3, 3)  # f_rest is channel-major: (channel, coefficient)
    rest += (strength[:, None, None] * coefficients[None, None, :]).astype(np.float32)
    out["features"][:, 3:] = rest.reshape(n, 9)
    return out


def glossy(rng, scale: float) -> dict[str, np.ndarray]:
    """Shiny objects whose colour changes with the view (``_shiny``): a ball, a torus and a box."""
    n = int(40000 * scale)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    ball = _shiny(rng, d * 0.35 + [-0.45, 0, 0], d, 0.35 * np.sqrt(4 * np.pi / n), [0.6, 0.1, 0.1])
    n = int(40000 * scale)
    a, b = rng.uniform(0, 2 * np.pi, n), rng.uniform(0, 2 * np.pi, n)
    big, small = 0.3, 0.1
    normals = np.stack([np.cos(a) * np.cos(b), np.sin(b), np.sin(a) * np.cos(b)], 1)
    centres = np.stack([big * np.cos(a), np.zeros(n), big * np.sin(a)], 1) + small * normals + [0.45, 0, 0]
    torus = _shiny(rng, centres, normals, np.sqrt(4 * np.pi**2 * big * small / n), [0.15, 0.3, 0.65])
    n = int(30000 * scale)
    face = rng.integers(0, 6, n)
    uv = rng.uniform(-1, 1, (n, 2))
    points, normals = np.zeros((n, 3)), np.zeros((n, 3))
    for axis in range(3):
        on = face % 3 == axis
        sign = np.where(face[on] < 3, 1.0, -1.0)
        others = [o for o in range(3) if o != axis]
        points[on, axis] = normals[on, axis] = sign
        points[on, others[0]], points[on, others[1]] = uv[on, 0], uv[on, 1]
    box = _shiny(rng, points * 0.2 + [0, 0.2, 0.5], normals, 0.2 * np.sqrt(24 / n), [0.75, 0.65, 0.2])
    return _concat([ball, torus, box])


def _wires(rng, paths: list[np.ndarray], radius: float, rgb, density: float) -> dict[str, np.ndarray]:
    """Thin round structures (cables, spokes, pickets) as a trainer leaves them: along each polyline of
    ``paths``, needles whose long axis follows the wire (standard deviations 2 to 4 radii along it
    and about one across it), about ``density`` of them per radius of length, jittered within the
    wire; a quarter of them a faint halo three times as wide and as long (opacity 0.03 to 0.25), the
    rest opaque."""
    points, tangents = [], []
    for path in paths:
        step = np.linalg.norm(np.diff(path, axis=0), axis=1)
        arc = np.concatenate([[0.0], np.cumsum(step)])
        count = max(2, int(arc[-1] / radius * density))
        at = np.sort(rng.uniform(0.0, arc[-1], count))
        segment = np.clip(np.searchsorted(arc, at, side="right") - 1, 0, len(step) - 1)
        t = ((at - arc[segment]) / np.maximum(step[segment], 1e-12))[:, None]
        points.append(path[segment] * (1 - t) + path[segment + 1] * t)
        tangents.append((path[segment + 1] - path[segment]) / np.maximum(step[segment], 1e-12)[:, None])
    means, x = np.concatenate(points), np.concatenate(tangents)
    n = len(means)
    z = np.cross(x, rng.normal(size=(n, 3)))
    z /= np.linalg.norm(z, axis=1, keepdims=True)
    halo = rng.random(n) < 0.25
    wide = np.where(halo, 3.0, 1.0)
    across = radius * wide * np.exp(rng.normal(scale=0.2, size=n))
    along = radius * wide * rng.uniform(2.0, 4.0, n)
    means = means + np.cross(x, z) * rng.normal(scale=0.4 * radius, size=(n, 1)) + z * rng.normal(scale=0.4 * radius, size=(n, 1))
    rest = rng.normal(scale=0.05, size=(n, 3 * ((SH_DEGREE + 1) ** 2 - 1)))
    colour = np.clip(np.asarray(rgb) + rng.normal(scale=0.03, size=(n, 3)), 0, 1)
    opacity = np.where(halo, rng.uniform(0.03, 0.25, n), rng.uniform(0.7, 0.99, n))
    return {
        "means": means.astype(np.float32),
        "rotations": _quat_from_axes(x, z).astype(np.float32),
        "log_scales": np.log(np.stack([along, across, across], 1)).astype(np.float32),
        "opacities": np.log(opacity / (1.0 - opacity)).astype(np.float32),
        "features": np.concatenate([(colour - 0.5) / SH_C0, rest], 1).astype(np.float32),
    }


def wires(rng, scale: float) -> dict[str, np.ndarray]:
    """Thin structures in front of a patterned wall (up -y): a picket fence with posts and rails,
    four sagging cables and a spoked wheel (``_wires``), the wall a ``_trained_surface``."""
    line = lambda a, b: np.stack([a, b]).astype(float)  # noqa: E731
    fence = [line([x, 0.6, 0.0], [x, -0.35, 0.0]) for x in np.linspace(-1.0, 1.0, 5)]
    rails = [line([-1.0, y, 0.02], [1.0, y, 0.02]) for y in (0.45, -0.2)]
    pickets = [line([x, 0.55, 0.035], [x, -0.3, 0.035]) for x in np.linspace(-0.97, 0.97, 40)]
    t = np.linspace(-1.0, 1.0, 64)[:, None]
    cables = [np.concatenate([1.25 * t, -0.75 + 0.18 * (np.cosh(1.2 * t) - 1) / (np.cosh(1.2) - 1) + 0.06 * k, np.full_like(t, 0.25 + 0.1 * k)], 1)
              for k in range(4)]  # fmt: skip
    angle = np.linspace(0.0, 2 * np.pi, 97)
    centre, wheel = np.array([0.35, 0.05, 0.45]), 0.3
    plane_u, plane_v = np.array([0.8, 0.0, -0.6]), np.array([0.0, 1.0, 0.0])
    rim = [centre + wheel * (np.cos(angle)[:, None] * plane_u + np.sin(angle)[:, None] * plane_v)]
    spokes = [line(centre + 0.02 * (np.cos(a) * plane_u + np.sin(a) * plane_v), centre + wheel * (np.cos(a) * plane_u + np.sin(a) * plane_v))
              for a in np.linspace(0.0, 2 * np.pi, 32, endpoint=False)]  # fmt: skip
    density = 2.0 * scale
    parts = [
        _wires(rng, fence, 0.02, [0.45, 0.3, 0.18], density),
        _wires(rng, rails, 0.012, [0.5, 0.35, 0.2], density),
        _wires(rng, pickets, 0.006, [0.9, 0.9, 0.85], density),
        _wires(rng, cables, 0.004, [0.08, 0.08, 0.09], density),
        _wires(rng, rim, 0.01, [0.1, 0.1, 0.1], density),
        _wires(rng, spokes, 0.0025, [0.75, 0.75, 0.78], density),
    ]
    n = int(30000 * scale)  # the wall: z = -0.6, x in [-1.3, 1.3], y in [-1, 0.7]
    uv = rng.random((n, 2))
    means = np.stack([uv[:, 0] * 2.6 - 1.3, uv[:, 1] * 1.7 - 1.0, np.full(n, -0.6)], 1)
    palette = np.array([[0.75, 0.72, 0.65], [0.6, 0.62, 0.7], [0.8, 0.65, 0.5], [0.55, 0.5, 0.45]])
    parts.append(_trained_surface(rng, means, np.tile([0, 0, 1.0], (n, 1)), np.sqrt(4.42 / n), _printed(uv[:, 0], uv[:, 1], 4, palette)))
    return _concat(parts)


SCENES = {
    "stress_fur": fur, "stress_grass": grass, "stress_panels": panels, "stress_backdrop": backdrop, "stress_unbounded": unbounded,
    "stress_texture": texture, "stress_glossy": glossy, "stress_wires": wires,
}  # fmt: skip


def write_scene(arrays: dict[str, np.ndarray], path: Path) -> None:
    """Writes a generated scene (means, rotations w first, log_scales, opacities, features) as an
    INRIA 3DGS PLY file and says on stderr how many splats it holds."""
    from nanogs_warp.io.ply import save_ply
    from nanogs_warp.splats import SplatSet

    a = arrays
    splats = SplatSet.from_numpy(a["means"], a["rotations"], a["log_scales"], a["opacities"], a["features"], device="cpu")
    save_ply(splats, path)
    print(f"{path.stem}: {splats.count:,} splats", file=sys.stderr)


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("out_dir", type=Path)
    parser.add_argument("--scale", type=float, default=1.0, help="multiplies every splat count")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    args.out_dir.mkdir(parents=True, exist_ok=True)
    for k, (name, make) in enumerate(SCENES.items()):
        write_scene(make(np.random.default_rng(args.seed * 100 + k), args.scale), args.out_dir / f"{name}.ply")
    return 0


if __name__ == "__main__":
    sys.exit(main())
