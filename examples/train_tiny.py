"""Train a camera from Python into a run folder, load it back and evaluate it: the `tiny` preset, in seconds.

    python examples/train_tiny.py [--out DIR] [--epochs 2]

The `tiny` preset (7 bands, 21-px PSF kernel, 3×3 CFA, a small RDN; the preset the tests train) is
trained jointly with its optics by `hsicam.engine.train.train`, which writes a run folder (config.yaml,
model.safetensors, metrics.jsonl, checkpoints/) as `hsicam train` does. The run is loaded again with
`load_run` and its validation scenes are scored as `hsicam evaluate --run` scores them (results.json,
.csv, .md). The synthetic data is generated into DIR/cache (colour-science needed once), not ~/.cache.
A tiny camera trained for seconds is no good camera: this shows the steps, not the quality.
"""

import argparse
import json
import tempfile
from pathlib import Path

from hsicam.config import load_config
from hsicam.data.pipeline import scene_dataset, split_dataset
from hsicam.engine.evaluate import evaluate_scenes, summarize, write_results
from hsicam.engine.train import train
from hsicam.runs.folder import load_run

parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
parser.add_argument("--out", type=Path, default=None, help="output folder (default: a new temporary folder)")
parser.add_argument("--epochs", type=int, default=2)
args = parser.parse_args()
out = args.out or Path(tempfile.mkdtemp(prefix="hsicam_train_"))
out.mkdir(parents=True, exist_ok=True)

# 1. The config: the preset, with keys changed as `--set` changes them (strict: a misspelt key is an error).
cfg = load_config("tiny", [f"data.cache_dir={out / 'cache'}", f"train.epochs={args.epochs}"])

# 2. Training: camera (DOE heights, CFA) and network together. A new run needs a new folder
#    (an existing run is continued with resume=True).
run = out / "run"
summary = train(cfg, run, resume=(run / "config.yaml").is_file(), progress=False)
print(f"trained {summary.get('step')} steps; files: {sorted(p.name for p in run.iterdir())}")
last = [json.loads(line) for line in (run / "metrics.jsonl").read_text(encoding="utf-8-sig").splitlines()][-1]
print(f"last record of metrics.jsonl: {json.dumps({k: last[k] for k in sorted(last)[:6]})}")

# 3. Load the run (the camera and network rebuilt from config.yaml, weights from model.safetensors).
cfg, system = load_run(run)  # (Config, CameraSystem), in eval mode
bands = cfg.bands.to_bands()
print(f"loaded: {system.camera.kind} camera, {len(bands)} bands, network {type(system.net).__name__} "
      f"({sum(p.numel() for p in system.net.parameters())} parameters)")

# 4. Evaluate on the run's validation scenes (the same split training used), with the camera's noise.
_, val = split_dataset(cfg.data, bands)
results = evaluate_scenes(system, scene_dataset(cfg.data, val, bands), [p.stem for p in val])
table = summarize(results, method="doe-learned", run=str(run))
write_results(out / "eval", table)  # results.json, results.csv, results.md
mean = table["mean"]
print(f"{len(results)} validation scenes: PSNR {mean['psnr']:.2f} dB, SSIM {mean['ssim']:.4f}, SAM {mean['sam']:.2f} deg")
print(f"wrote {out}")
