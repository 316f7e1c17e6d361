"""Camera benchmark (issue 2): prints one JSON object.

- PSF stack of the paper optics (31 bands, 141 px kernel): forward, and forward+backward,
  in float32 and float64.
- Camera forward+backward for a batch of 4 × 31 × 256 × 256 sensor pixels (valid mode, scene
  396 × 396) with the paper kernel: the convolution/CFA part alone (fixed PSF) and the whole
  camera (PSF recomputed from the DOE, as in training).
- FFT versus direct (F.conv2d) convolution on the same batch, forward only.

Run: `.venv/bin/python benchmarks/bench_camera.py [--repeats N]`. Timings are medians.
"""

from __future__ import annotations

import argparse
import json
import platform

import torch
import torch.nn.functional as F

from hsicam.cameras import DOECamera
from hsicam.config import load_config
from hsicam.optics.convolution import conv_valid
from timing import median_time, positive_int


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--repeats", type=positive_int, default=5)
    ap.add_argument("--batch", type=positive_int, default=4)
    ap.add_argument("--size", type=positive_int, default=256)
    ap.add_argument("--threads", type=positive_int, default=None, help="torch CPU threads (default: torch's choice)")
    args = ap.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    torch.manual_seed(0)
    result: dict = {"torch": torch.__version__, "threads": torch.get_num_threads(), "machine": platform.machine()}

    cam = DOECamera.from_config(load_config())
    k = cam.kernel_px
    for dtype, name in ((torch.float32, "float32"), (torch.float64, "float64")):
        cam = cam.to(dtype)
        result[f"psf_forward_s_{name}"] = median_time(lambda: cam.psf(), args.repeats, 1)

        def fwd_bwd():
            cam.zero_grad(set_to_none=True)
            cam.psf().sum().backward()

        result[f"psf_forward_backward_s_{name}"] = median_time(fwd_bwd, args.repeats, 1)
    cam = cam.float()
    x = torch.rand(args.batch, len(cam.bands), args.size + k - 1, args.size + k - 1)
    psf_fixed = cam.psf().detach().requires_grad_()

    def conv_fb():
        cam.zero_grad(set_to_none=True)
        cam.A(x, psf_fixed).sum().backward()

    def camera_fb():
        cam.zero_grad(set_to_none=True)
        cam(x).sum().backward()

    result["batch"] = [args.batch, len(cam.bands), args.size, args.size]
    result["kernel_px"] = k
    result["convolution_cfa_forward_backward_s"] = median_time(conv_fb, args.repeats, 1)
    result["camera_forward_backward_s"] = median_time(camera_fb, args.repeats, 1)

    # Direct convolution of the whole batch is ~160 GFLOP; compare on a 1 × 4-band slice
    # (the work per band image is the same, so the ratio carries over).
    psf = psf_fixed.detach()[:4]
    xs = x[:1, :4].contiguous()
    weight = torch.flip(psf, dims=(-2, -1)).unsqueeze(1)
    with torch.no_grad():
        t_fft = median_time(lambda: conv_valid(xs, psf), args.repeats, 1)
        t_direct = median_time(lambda: F.conv2d(xs, weight, groups=psf.shape[0]), 2, 1)
    result["direct_vs_fft_slice"] = [1, 4, args.size, args.size]
    result["conv_fft_forward_s_slice"] = t_fft
    result["conv_direct_forward_s_slice"] = t_direct
    result["direct_over_fft_ratio"] = t_direct / t_fft
    result["targets"] = {"psf_forward_backward_s": 0.3, "camera_forward_backward_s": 0.5}
    print(json.dumps(result, indent=2))


if __name__ == "__main__":
    main()
