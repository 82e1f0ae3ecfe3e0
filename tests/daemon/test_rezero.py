"""The software zero after a bias taken under a grasp (slipd.daemon.rezero)."""

from __future__ import annotations

import numpy as np

from slipd.daemon.rezero import LoadedZero

RATE = 1000
ZERO = np.zeros((1, 9, 3))


def _blocks(fz: float, seconds: float, *, seed: int = 0, shear: float = 0.0, block: float = 5) -> list[np.ndarray]:
    """Raw frames as the sensor sends them after the bias, in blocks of ``block``: every pillar at ``fz`` (N)."""
    rng = np.random.default_rng(seed)
    n = round(seconds * RATE)
    x = rng.normal(0.0, 0.01, (n, 1, 9, 3))
    x[..., 2] += fz
    x[..., 0] += shear
    step = int(block)
    return [x[i : i + step] for i in range(0, n, step)]


def _feed(z: LoadedZero, blocks: list[np.ndarray], in_contact: bool = False) -> np.ndarray | None:
    found = None
    for b in blocks:
        out = z.push(b, ZERO, in_contact)
        found = out if out is not None else found
    return found


def test_the_free_air_after_the_release_becomes_the_zero() -> None:
    """Zeroed under a 1.5 N-per-pillar grasp (13.5 N read at the loss): after the release every pillar reads -1.5 N
    and the held load's shear the other way; that still stretch is the new offset, shear included."""
    z = LoadedZero(1, RATE)
    z.arm([13.5])
    assert _feed(z, _blocks(0.0, 2.0)) is None  # the grasp goes on, zeroed: nothing to do
    assert _feed(z, _blocks(-1.5, 0.2, shear=-0.4)) is None  # released, not yet still for long enough
    offset = _feed(z, _blocks(-1.5, 0.3, seed=1, shear=-0.4))
    assert offset is not None and offset.shape == (1, 9, 3)
    assert np.abs(offset[..., 2] + 1.5).max() < 0.02 and np.abs(offset[..., 0] + 0.4).max() < 0.02
    assert not z.armed  # once


def test_a_grip_that_only_eased_and_a_grasp_in_contact_are_not_the_free_air() -> None:
    z = LoadedZero(1, RATE)
    z.arm([13.5])
    assert _feed(z, _blocks(-0.3, 1.0)) is None  # eased by 2.7 N in all: the object is still held
    assert _feed(z, _blocks(-1.5, 1.0), in_contact=True) is None  # the gate sees a contact: no zero from it
    assert z.armed
    assert _feed(z, _blocks(-1.5, 0.5)) is not None


def _ramp(start: float, end: float, seconds: float, block: int = 5) -> list[np.ndarray]:
    x = np.concatenate(_blocks(0.0, seconds, seed=2, block=seconds * RATE))
    x[..., 2] += np.linspace(start, end, len(x))[:, None, None]
    return [x[i : i + block] for i in range(0, len(x), block)]


def test_a_jaw_still_opening_is_not_the_free_air() -> None:
    """A release over 1.5 s (1 N/s per pillar): the zero comes from the still air after it, not from the ramp."""
    z = LoadedZero(1, RATE)
    z.arm([13.5])
    assert _feed(z, _ramp(0.0, -1.5, 1.5)) is None
    offset = _feed(z, _blocks(-1.5, 0.5, seed=3))
    assert offset is not None and np.abs(offset[..., 2] + 1.5).max() < 0.02
    # One block of 400 frames (after a stall) holding a whole release: judged by its chunks, not taken whole.
    z.arm([13.5])
    assert _feed(z, _ramp(0.0, -3.0, 0.4, block=400)) is None and z.armed


def test_a_broken_signal_is_not_the_free_air() -> None:
    z = LoadedZero(1, RATE)
    z.arm([13.5])
    broken = _blocks(-1.5, 1.0)
    for b in broken[::20]:
        b[0, 0, 4, 2] = np.nan  # a NaN every 0.1 s restarts the stretch
    assert _feed(z, broken) is None
    assert z.armed


def test_disarmed_it_does_nothing() -> None:
    z = LoadedZero(1, RATE)
    assert _feed(z, _blocks(-1.5, 1.0)) is None  # never armed: the zero is a free-air one
    z.arm([13.5])
    z.disarm()
    assert _feed(z, _blocks(-1.5, 1.0)) is None


def test_two_fingers_are_zeroed_together_from_the_one_that_shows_the_release() -> None:
    z = LoadedZero(2, RATE)
    z.arm([13.5, 0.0])
    rng = np.random.default_rng(3)
    x = rng.normal(0.0, 0.01, (400, 2, 9, 3))
    x[:, 0, :, 2] -= 1.5  # the loaded finger reads its old load below zero; the other one sat at zero already
    offset = None
    for i in range(0, 400, 4):
        out = z.push(x[i : i + 4], np.zeros((2, 9, 3)), False)
        offset = out if out is not None else offset
    assert offset is not None and offset.shape == (2, 9, 3)
    assert np.abs(offset[0, :, 2] + 1.5).max() < 0.02 and np.abs(offset[1, :, 2]).max() < 0.02


def test_frames_before_a_grasp_do_not_enter_the_stretch_after_it() -> None:
    """Five frames of a part-filled chunk, then a block in contact: the stretch that follows is its own frames
    alone (the part-filled chunk's sum was kept across the break and shifted the zero by a few mN)."""
    z = LoadedZero(1, RATE)
    z.arm([10.0])
    assert z.push(np.full((5, 1, 9, 3), 0.09), ZERO, False) is None
    assert z.push(np.zeros((5, 1, 9, 3)), ZERO, True) is None
    free = np.zeros((300, 1, 9, 3))
    free[:, :, :, 2] = -0.7  # 6.3 N below the zero: released
    offset = _feed(z, [free[i : i + 10] for i in range(0, 300, 10)])
    assert offset is not None and np.allclose(offset, free[0], atol=1e-6)
