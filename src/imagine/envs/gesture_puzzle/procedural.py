"""The built-in procedural renderer of image fragments (docs/design.md section 1).

The paper photographed, with the robot's camera, 16 fragments for every (cube, arrow direction)
microstate and 50 for every hand microstate (which cube is pointed at), then composed one random
fragment per microstate into a grayscale scene. This module draws such fragments instead of
photographing them: a cube seen from above with a painted arrow, and a human arm whose index
finger points up at one cube, each with the variation a camera gives (position and scale jitter,
small rotations, lighting, stroke width, blur and sensor noise).

Every fragment is a pure function of ``(seed, kind, microstate, k)``, so a pool is deterministic
for a seed and a fragment does not change when the pool is made larger.

Layout (pixels, grayscale): a cube fragment is ``CUBE_SHAPE`` = 96 x 96; the hand fragment spans
the width of the three cubes below them, ``HAND_SHAPE`` = 48 x 288; the scene is 144 x 288, the
robot's side at the top, the human's at the bottom.
"""

from __future__ import annotations

import math

import numpy as np
from PIL import Image, ImageDraw, ImageFilter

CUBE_SHAPE = (96, 96)
HAND_SHAPE = (48, 288)
_SUPERSAMPLE = 3
_KIND_CUBE, _KIND_HAND = 0, 1


def _rng(seed: int, kind: int, *ids: int) -> np.random.Generator:
    return np.random.default_rng([seed, kind, *ids])


def _transform(points: np.ndarray, angle: float, scale: float, center: tuple[float, float]):
    """Rotate (clockwise on screen, y pointing down), scale and move points of shape (n, 2)."""
    c, s = math.cos(angle), math.sin(angle)
    rot = np.array([[c, -s], [s, c]])
    return [tuple(p) for p in (points @ rot.T) * scale + np.asarray(center)]


def _background(rng: np.random.Generator, shape: tuple[int, int]) -> np.ndarray:
    """A table top under uneven light: a base gray level with a linear gradient."""
    h, w = shape
    base = rng.uniform(60, 80)
    gy, gx = rng.uniform(-8, 8, size=2)
    y = np.linspace(-0.5, 0.5, h)[:, None]
    x = np.linspace(-0.5, 0.5, w)[None, :]
    return base + gy * y + gx * x


def _finish(rng: np.random.Generator, drawing: Image.Image, background: np.ndarray) -> np.ndarray:
    """Downsample the supersampled drawing, light it, blur it and add sensor noise."""
    h, w = background.shape
    small = drawing.resize((w, h), Image.Resampling.BOX)
    rgba = np.asarray(small, dtype=np.float64)
    value, alpha = rgba[..., 0], rgba[..., 1] / 255.0
    img = alpha * value + (1 - alpha) * background
    img = img * rng.uniform(0.94, 1.06) + rng.uniform(-4, 4)  # exposure and offset
    blurred = Image.fromarray(np.clip(np.rint(img), 0, 255).astype(np.uint8)).filter(
        ImageFilter.GaussianBlur(radius=rng.uniform(0.0, 1.0))
    )
    img = np.asarray(blurred, dtype=np.float64) + rng.normal(0, rng.uniform(1.5, 5.0), size=(h, w))
    return np.clip(np.rint(img), 0, 255).astype(np.uint8)


# The arrow in unit coordinates, pointing UP (toward the robot, negative y): a shaft and a head.
def _arrow_polygon(stroke: float, head: float) -> np.ndarray:
    half = stroke / 2
    return np.array(
        [
            (-half, 0.36),
            (half, 0.36),
            (half, -0.06),
            (head / 2, -0.06),
            (0.0, -0.40),
            (-head / 2, -0.06),
            (-half, -0.06),
        ]
    )


_SQUARE = np.array([(-0.5, -0.5), (0.5, -0.5), (0.5, 0.5), (-0.5, 0.5)])
# Each cube has its own paint, so the three pools differ a little, as real cubes would.
_CUBE_SHADE = (246.0, 242.0, 250.0)


def cube_fragment(seed: int, cube: int, direction: int, k: int) -> np.ndarray:
    """Fragment ``k`` of cube ``cube`` with its arrow in ``direction`` (0 up .. 3 left)."""
    rng = _rng(seed, _KIND_CUBE, cube, direction, k)
    h, w = CUBE_SHAPE
    ss = _SUPERSAMPLE
    background = _background(rng, CUBE_SHAPE)
    # (value, alpha) layers: value is the gray level of what is drawn, alpha its coverage.
    drawing = Image.new("LA", (w * ss, h * ss), (0, 0))
    pen = ImageDraw.Draw(drawing)

    size = 74 * rng.uniform(0.97, 1.03) * ss
    center = (
        (w / 2 + rng.uniform(-2, 2)) * ss,
        (h / 2 - 4 + rng.uniform(-2, 2)) * ss,
    )
    tilt = math.radians(rng.uniform(-4, 4))
    face = float(np.clip(_CUBE_SHADE[cube] + rng.uniform(-6, 6), 0, 255))
    side = face * rng.uniform(0.5, 0.65)

    # The side of the cube facing the camera, then its top face with the arrow.
    side_center = (center[0], center[1] + 0.12 * size)
    pen.polygon(_transform(_SQUARE, tilt, size, side_center), fill=(int(side), 255))
    pen.polygon(_transform(_SQUARE, tilt, size, center), fill=(int(face), 255))
    stroke = rng.uniform(0.20, 0.28)
    arrow = _arrow_polygon(stroke, head=rng.uniform(0.58, 0.70))
    ink = int(rng.uniform(0, 25))
    angle = direction * math.pi / 2 + tilt
    pen.polygon(_transform(arrow, angle, size * rng.uniform(0.92, 1.05), center), fill=(ink, 255))
    return _finish(rng, drawing, background)


def hand_fragment(seed: int, pointed: int, k: int) -> np.ndarray:
    """Fragment ``k`` of the human's arm, index finger pointing up at cube ``pointed``."""
    rng = _rng(seed, _KIND_HAND, pointed, k)
    h, w = HAND_SHAPE
    ss = _SUPERSAMPLE
    background = _background(rng, HAND_SHAPE)
    drawing = Image.new("LA", (w * ss, h * ss), (0, 0))
    pen = ImageDraw.Draw(drawing)

    cube_w = CUBE_SHAPE[1]
    tip_x = cube_w * (pointed + 0.5) + rng.uniform(-3, 3)
    # The human sits at the middle of the bottom edge: the arm leans from there toward the cube.
    base_x = tip_x + (w / 2 - tip_x) * rng.uniform(0.1, 0.3) + rng.uniform(-6, 6)
    fist_y = h * rng.uniform(0.55, 0.68)
    skin = int(rng.uniform(195, 235))
    sleeve = int(np.clip(skin - rng.uniform(60, 110), 0, 255))
    arm_w = rng.uniform(30, 38)

    def px(x: float, y: float) -> tuple[float, float]:
        return (x * ss, y * ss)

    # Sleeve from the bottom edge, bare forearm up to the wrist.
    dx = tip_x - base_x
    wrist = (base_x + 0.85 * dx, fist_y + 6)
    elbow = (base_x + 0.35 * dx, h + 4 - 0.35 * (h + 4 - wrist[1]))
    pen.line([px(base_x, h + 6), px(*elbow)], fill=(sleeve, 255), width=int(arm_w * ss))
    pen.line([px(*elbow), px(*wrist)], fill=(skin, 255), width=int(arm_w * 0.8 * ss))
    # Fist: palm, curled fingers as knuckle bumps and a thumb; the index finger points up.
    fist_r = arm_w * rng.uniform(0.65, 0.75)
    fx, fy = tip_x, fist_y
    pen.ellipse(
        [px(fx - fist_r, fy - fist_r * 0.7), px(fx + fist_r, fy + fist_r * 0.8)], fill=(skin, 255)
    )
    knuckle = fist_r * 0.42
    side = 1 if rng.random() < 0.5 else -1
    for j in range(3):
        kx = fx + side * (j + 1) * knuckle * 0.9
        pen.ellipse(
            [
                px(kx - knuckle, fy - fist_r * 0.75 - knuckle * 0.4),
                px(kx + knuckle, fy - fist_r * 0.75 + knuckle * 1.4),
            ],
            fill=(skin - 12, 255),
        )
    thumb = (fx - side * fist_r * 0.9, fy + fist_r * 0.1)
    pen.ellipse(
        [
            px(thumb[0] - knuckle, thumb[1] - knuckle * 1.3),
            px(thumb[0] + knuckle, thumb[1] + knuckle * 1.3),
        ],
        fill=(skin - 6, 255),
    )
    finger_w = rng.uniform(11, 14)
    tip_y = rng.uniform(1.0, 5.0)
    lean = rng.uniform(-2, 2)
    pen.line(
        [px(fx, fy - fist_r * 0.5), px(fx + lean, tip_y + finger_w / 2)],
        fill=(skin, 255),
        width=int(finger_w * ss),
    )
    r = finger_w / 2
    pen.ellipse([px(fx + lean - r, tip_y), px(fx + lean + r, tip_y + 2 * r)], fill=(skin, 255))
    return _finish(rng, drawing, background)
