"""A network of your own: register it as a `model.kind`, build a CameraSystem with it, train a few steps.

    python examples/custom_network.py [--out DIR] [--steps 20]

A small physics-aware network (the sensor image spread into the bands by the camera's own sensor code,
the CFA, then a residual conv stack) is registered with `hsicam.models.register_network`, as the shipped
networks are (docs/architecture.md, "Adding a network"). `model.kind=code_cnn` then builds it through
`CameraSystem.from_config`, on the `tiny` preset's camera. A few Adam steps on random scenes train
network and optics together; the weights are saved to DIR/code_cnn.safetensors.
"""

import argparse
import tempfile
from pathlib import Path

import torch
from safetensors.torch import save_file
from torch import nn

from hsicam.config import load_config
from hsicam.engine.train import build_optimizer
from hsicam.models import CameraSystem, register_network
from hsicam.models.context import conv_receptive_radius

FEATURES = 16  # a kind registered outside hsicam has no section in the config: its settings are its own


class CodeCNN(nn.Module):
    """sensor (B, 1, H, W) -> cube (B, C, H, W): sensor × code (each pixel's light given to the bands its
    filter passes), refined by a residual stack of 3×3 convs."""

    def __init__(self, bands: int, features: int = FEATURES) -> None:
        super().__init__()
        self.body = nn.Sequential(nn.Conv2d(bands, features, 3, padding=1), nn.ReLU(),
                                  nn.Conv2d(features, features, 3, padding=1), nn.ReLU(),
                                  nn.Conv2d(features, bands, 3, padding=1))

    def forward(self, sensor, camera, origin=(0, 0)):
        code = camera.sensor_code(sensor.shape[-2], sensor.shape[-1], origin).to(sensor.dtype)  # (C, H, W)
        x = sensor * code / code.square().sum(0).clamp_min(1e-6)  # least-squares spread of each pixel over bands
        return x + self.body(x)

    @property
    def context_px(self) -> int:  # the halo tiled inference needs: 3 convs of reach 1
        return conv_receptive_radius(self.body)


def code_cnn_parameters(cfg, camera) -> int:  # closed form, for the memory check before anything is built
    c, f = len(camera.bands), FEATURES
    return (9 * c * f + f) + (9 * f * f + f) + (9 * f * c + c)


@register_network("code_cnn", parameters=code_cnn_parameters, sizes=("features",))
def build_code_cnn(cfg, camera):
    return CodeCNN(len(camera.bands))


parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
parser.add_argument("--out", type=Path, default=None, help="output folder (default: a new temporary folder)")
parser.add_argument("--steps", type=int, default=20)
args = parser.parse_args()
out = args.out or Path(tempfile.mkdtemp(prefix="hsicam_net_"))
out.mkdir(parents=True, exist_ok=True)

torch.manual_seed(0)
cfg = load_config("tiny", ["model.kind=code_cnn"])
system = CameraSystem.from_config(cfg)  # camera from camera.kind, network from model.kind
cam, n_params = system.camera, sum(p.numel() for p in system.net.parameters())
assert n_params == code_cnn_parameters(cfg, cam)
print(f"{type(system.net).__name__}: {n_params} parameters, context {system.net.context_px} px; "
      f"camera {cam.kind}, {len(cam.bands)} bands, margin {cam.margin} px")

# Forward pass: scene (B, C, S, S) -> (reconstruction, sensor), both S - margin px ("valid" boundary).
scenes = torch.rand(8, len(cam.bands), 32 + cam.margin, 32 + cam.margin)
rec, sensor = system(scenes[:2])
print(f"forward: scene {tuple(scenes[:2].shape)} -> sensor {tuple(sensor.shape)} -> cube {tuple(rec.shape)}")

# A few training steps: L1 (the paper's loss) against the scene under the sensor. build_optimizer gives
# Adam the network and the camera's groups (DOE heights, CFA) at the config's learning rates (train.lr,
# train.doe_lr_nm, train.cfa_lr): the optics train too.
opt = build_optimizer(cfg, system)
system.train()
heights = cam.param_groups()["doe"][0]  # the DOE's height map (m), a trained parameter
doe0 = heights.detach().clone()
losses = []
for step in range(args.steps):
    batch = scenes[torch.randint(0, len(scenes), (4,))]
    rec, _ = system(batch)
    loss = (rec - system.target(batch)).abs().mean()
    opt.zero_grad()
    loss.backward()
    opt.step()
    losses.append(loss.item())
doe_moved_nm = float((heights.detach() - doe0).abs().max()) * 1e9
print(f"DOE heights moved up to {doe_moved_nm:.2f} nm")
print(f"L1 loss: step 1 {losses[0]:.4f} -> step {len(losses)} {losses[-1]:.4f}")
save_file({k: v.contiguous() for k, v in system.state_dict().items()}, str(out / "code_cnn.safetensors"))
print(f"wrote {out / 'code_cnn.safetensors'}")
