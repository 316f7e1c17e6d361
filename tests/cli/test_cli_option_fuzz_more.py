"""Hostile option values found by session 59's fuzzing of the commands that train or sweep (fuzz11a).

``reconstruct --full-well-e 1000 --read-noise-e 1e308`` (and ``--full-well-e 1e-300 --read-noise-e 2``) ended in an
OverflowError traceback of the noise variance (r/E)², after the run was loaded and the network had run; ``--full-well-e
1e-300`` alone reconstructed (exit 0) with an infinite noise variance. ``tolerance --shift-subsamples 1000000000000``
(or 2**70) never came back: the FFT length of its pupil was searched by trying n, n + 1, … for a 7-smooth number, whose
gaps grow with n, in the very check that refuses that pupil for its memory (``train --set
camera.psf.pupil_oversample=...`` alike)."""

from __future__ import annotations

import signal

import numpy as np
import pytest

from cli_helpers import error_line, run_cli_in_process, tree_snapshot
from test_cli_option_fuzz import capture  # noqa: F401 - the fixture (a 48×48 float capture .npy), as there


class Hung(AssertionError):
    """Raised by :func:`guarded`'s alarm (the command's error boundary re-raises it, as any bug)."""


def guarded(fn, *args, seconds: int = 30):
    """``fn(*args)``, failing the test instead of hanging when it runs past ``seconds`` (far above what it takes when
    it works)."""

    def hung(signum, frame):
        raise Hung()

    old = signal.signal(signal.SIGALRM, hung)
    signal.alarm(seconds)
    try:
        return fn(*args)
    except Hung:
        pass  # failed below, outside this handler: pytest cannot show the frame a signal interrupted
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, old)
    pytest.fail(f"{getattr(fn, '__name__', fn)} still running after {seconds} s")


@pytest.mark.parametrize("options, said", [
    (("--full-well-e", "1000", "--read-noise-e", "1e308"),
     "--read-noise-e must be at most --full-well-e (1000 e-: read noise above the full scale buries any signal, as "
     "camera.sensor.read_noise_e), got 1e+308"),
    (("--full-well-e", "1e-300", "--read-noise-e", "2"),
     "--full-well-e must be a positive number of electrons in [1, 1e+12] (at the white level; sensors hold 10^3 to "
     "10^6, as camera.sensor.full_well_e), got 1e-300"),
    (("--full-well-e", "1e-300"),
     "--full-well-e must be a positive number of electrons in [1, 1e+12] (at the white level; sensors hold 10^3 to "
     "10^6, as camera.sensor.full_well_e), got 1e-300"),
    (("--full-well-e", "1e308"),
     "--full-well-e must be a positive number of electrons in [1, 1e+12] (at the white level; sensors hold 10^3 to "
     "10^6, as camera.sensor.full_well_e), got 1e+308"),
])
def test_reconstruct_refuses_capture_noise_outside_the_configs_range(capture, tmp_path, options, said):
    """The range camera.sensor takes (full well in [1, 1e12] e-, read noise at most the full well), in one line naming
    the option, before any work and without writing anything."""
    before = tree_snapshot(tmp_path)
    res = run_cli_in_process("reconstruct", str(capture), "--run", "pretrained:standard", "--out",
                             str(tmp_path / "est.h5"), *options)
    assert error_line(res) == f"hsicam: error: {said}"
    assert tree_snapshot(tmp_path) == before


def test_reconstruct_still_takes_a_read_noise_equal_to_the_full_well(capture, tmp_path):
    """The bound's edge (read noise = full well, as the config allows) reconstructs, the values in the cube's metadata."""
    import json

    import h5py

    out = tmp_path / "est.h5"
    res = run_cli_in_process("reconstruct", str(capture), "--run", "pretrained:standard", "--out", str(out),
                             "--full-well-e", "50", "--read-noise-e", "50")
    assert res.returncode == 0, res.stderr
    with h5py.File(out, "r") as f:
        meta = json.loads(f.attrs["metadata_json"])
    assert meta["noise_full_well_e"] == 50.0 and meta["noise_read_noise_e"] == 50.0


def smooth7_reference(n: int) -> int:
    """The smallest 2^a·3^b·5^c·7^d >= n, from the sorted set of every such number up to the power of 2 >= n."""
    top = 1 << max(0, n - 1).bit_length()  # a power of 2 >= n: the answer is at most it
    found = {1}
    for p in (2, 3, 5, 7):
        grown = set()
        for v in found:
            while v <= top:
                grown.add(v)
                v *= p
        found = grown
    return min(v for v in found if v >= n)


@pytest.mark.parametrize("n", [1, 2, 11, 13, 665, 2 * 333 - 1, 10007, 2 * 41 * 10**12 - 1, 2 * 41 * 2**70 - 1,
                               10**30 + 1])
def test_fast_fft_length_is_the_smallest_7_smooth_length(n):
    from hsicam.optics.sampling import fast_fft_length

    assert guarded(fast_fft_length, n) == smooth7_reference(n)


@pytest.mark.parametrize("q", [str(10**12), str(2**70)])
def test_tolerance_refuses_a_huge_shift_subsampling_at_once(tmp_path, q):
    """The memory check refuses such a pupil in one line naming the option; it used to search its FFT length for
    hours first."""
    data = tmp_path / "scene.npy"
    np.save(data, np.random.default_rng(0).random((7, 32, 32)).astype(np.float32))
    out = tmp_path / "tol"
    res = guarded(run_cli_in_process, "tolerance", "--run", "pretrained:standard", "--out", str(out), "--data",
                  str(data), "--shift-cells", "0.5", "--shift-subsamples", q, "--sigma-height-nm", "0", "--levels", "2",
                  "--sensor-distance-um", "0")
    line = error_line(res)
    assert line.startswith(f"hsicam: error: --shift-subsamples {q}: the misalignment study's pupil of {q} samples per "
                           "DOE cell cannot be simulated here (the PSF sampling plan needs at least "), line
    assert not out.exists()
