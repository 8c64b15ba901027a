"""What a real camera does to the clean render (issue 51): per-camera colour gains, sensor noise, motion blur.

Order, as in a camera: the scene integrated over the shutter time (motion blur: `shutter_offsets`,
`shutter_vertices`), scaled per channel by the camera's exposure and white balance (`camera_gains`), sensor noise
added (`sensor_image`), then rounded to 8 bits and JPEG-compressed by the writer (`synth.capture`). Every random
choice has its own seeded stream (`numpy.random.default_rng([seed, stream, ...])`, streams 11-13), apart from those of
the scene, cameras and textures: switching an imperfection on changes nothing else of the capture.
"""

from __future__ import annotations

import numpy as np

GAIN_STREAM, NOISE_STREAM, PLATE_NOISE_STREAM = 11, 12, 13


def camera_gains(seed: int, cams: int, exposure_ev: float, white_balance: float) -> np.ndarray:
    """[cams, 3] per-channel gains: 2^(e_c + w_ck), e_c ~ N(0, exposure_ev^2), w_ck ~ N(0, white_balance^2) stops.
    The draws do not depend on the two spreads (exposure alone and white balance alone use the same numbers)."""
    rng = np.random.default_rng([seed, GAIN_STREAM])
    e = rng.standard_normal(cams)  # [cams]
    w = rng.standard_normal((cams, 3))  # [cams, 3]
    return 2.0 ** (exposure_ev * e[:, None] + white_balance * w)


def sensor_image(img: np.ndarray, gain: np.ndarray, noise_std: float, rng: np.random.Generator | None
                 ) -> np.ndarray:
    """The clean render [H, W, 3] in [0, 1] as camera c records it: x gain [3], + N(0, noise_std^2), clipped to
    [0, 1] (float32)."""
    out = img.astype(np.float64) * np.asarray(gain, np.float64).reshape(1, 1, 3)
    if noise_std > 0:
        assert rng is not None, "sensor noise needs a generator"
        out = out + rng.normal(0.0, noise_std, out.shape)
    return np.clip(out, 0.0, 1.0).astype(np.float32)


def noise_rng(seed: int, cam: int, frame: int) -> np.random.Generator:
    """The sensor noise stream of camera `cam`'s image of written frame `frame`."""
    return np.random.default_rng([seed, NOISE_STREAM, cam, frame])


def plate_rng(seed: int, cam: int) -> np.random.Generator:
    """The sensor noise stream of camera `cam`'s background plate."""
    return np.random.default_rng([seed, PLATE_NOISE_STREAM, cam])


def shutter_offsets(shutter_s: float, frame_interval_s: float, samples: int) -> np.ndarray:
    """[samples] times (in written-frame intervals) spread evenly over the shutter time centred on the frame; an odd
    `samples` includes 0 (the frame's own instant). shutter 0: [0.]."""
    if shutter_s <= 0:
        return np.zeros(1)
    span = shutter_s / frame_interval_s
    return ((np.arange(samples) + 0.5) / samples - 0.5) * span


def shutter_vertices(verts: np.ndarray, k: int, tau: float, segment: tuple[int, int]) -> np.ndarray:
    """Vertices [V, 3] at time k + tau (written-frame units, |tau| <= 1), interpolated linearly towards the
    neighbouring written frame of the same segment [start, stop) (train or test: never across the unwritten
    transition); at a segment's end the other neighbour's motion is mirrored. verts [frames, V, 3]."""
    if tau == 0:
        return verts[k]
    start, stop = segment
    step = 1 if tau > 0 else -1
    if not start <= k + step < stop:  # no neighbour on that side: mirror the other side's motion
        step = -step
        if not start <= k + step < stop:  # a one-frame segment: no motion to blur
            return verts[k]
        return verts[k] - abs(tau) * (verts[k + step] - verts[k])
    return verts[k] + abs(tau) * (verts[k + step] - verts[k])
