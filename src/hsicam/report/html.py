"""`hsicam report DIR`: a self-contained HTML report (relative image paths) of an evaluation
folder (``results.json`` [+ ``cubes/``]) or an experiment folder (``experiment.json``).

Only a complete folder is reported: it must carry the completion marker its command writes last
(:func:`hsicam.io.is_complete`) and hold well-formed JSON; anything else is one
:class:`~hsicam.errors.InputError` line. ``DIR/report/`` is written under a temporary name and
renamed into place at the end, so a failed report leaves nothing behind."""

from __future__ import annotations

import html
import json
import math
import re
import urllib.parse
from pathlib import Path

import matplotlib
import numpy as np
from matplotlib.figure import Figure
from matplotlib.patches import Rectangle

from hsicam.errors import ConfigError, InputError
from hsicam.io import (
    OutputLock, atomic_open, atomic_output, is_complete, json_number, nan_for_null, save_figure,
)
from hsicam.report.reconstruction import cube_rgb, plot_training_curves, spectra_exponent
from hsicam.spectral import Bands

CSS = """body{font-family:system-ui,sans-serif;max-width:1200px;margin:2em auto;padding:0 1em;color:#222}
table{border-collapse:collapse;margin:1em 0}td,th{border:1px solid #ccc;padding:4px 8px;text-align:right}
th{background:#f3f3f3}td:first-child,th:first-child{text-align:left}img{max-width:100%;border:1px solid #eee}
.note{color:#555;font-size:90%}h2{border-bottom:1px solid #ddd;padding-bottom:4px}"""

# Sets document.title to "report-ok N" or "report-missing K" once every image has loaded or failed,
# so a headless browser (and the tests) can tell a complete report from one with broken images.
CHECK_IMAGES = """<script>
window.addEventListener('load', function () {
  var imgs = Array.prototype.slice.call(document.images);
  var bad = imgs.filter(function (i) { return !(i.complete && i.naturalWidth > 0); });
  document.title = bad.length ? 'report-missing ' + bad.length : 'report-ok ' + imgs.length;
  document.body.setAttribute('data-images', document.title);
});
</script>"""


def build_report(folder: str | Path) -> Path:
    """Write ``folder/report/index.html`` and its PNGs; returns the index path. Holds ``folder``'s output lock
    (:class:`~hsicam.io.OutputLock`) while it reads and writes: an ``evaluate``/``experiment`` rewriting the folder,
    which hold it from their start, is refused in one line naming its pid, either way round (a report built
    meanwhile was lost with the old folder, failed naming its own PNG, or showed the old scores beside the new
    results.json; session 73's hunt)."""
    folder = Path(folder)
    if not folder.is_dir():
        if folder.exists():
            raise InputError(f"{folder}: a file, not a folder: give the folder of an evaluation or an experiment (the "
                             f"one holding results.json or experiment.json{', e.g. ' + str(folder.parent) if folder.name in ('results.json', 'experiment.json') else ''})")
        raise InputError(f"{folder}: no such folder")
    with OutputLock(folder, command="report") as lock:
        lock.acquire()
        return _build_report(folder)


def _build_report(folder: Path) -> Path:
    """:func:`build_report` of an existing folder, its lock held."""
    if (folder / "experiment.json").is_file():
        source, kind = folder / "experiment.json", "experiment"
    elif (folder / "results.json").is_file():
        source, kind = folder / "results.json", "evaluation"
    else:
        raise InputError(f"{folder}: neither results.json (hsicam evaluate) nor experiment.json (hsicam experiment)")
    if not is_complete(folder):
        raise InputError(f"{folder}: incomplete {kind} folder (no completion marker: the command that wrote it failed "
                         f"or was interrupted); run `hsicam {'experiment' if kind == 'experiment' else 'evaluate'}` again")
    data = _read_json(source)
    _check_fields(source, data, kind)
    with atomic_output(folder / "report", overwrite=True, marker={"command": "report"}) as out:
        try:
            body = _experiment_sections(folder, out, data) if kind == "experiment" else _evaluation_sections(folder, out, data)
        except InputError:  # a file the page reads besides this one (a saved cube) names itself
            raise
        except KeyError as exc:  # a field the checks above do not cover
            raise InputError(f"{source}: corrupt {source.name} (the field {exc} is missing)") from None
        except (TypeError, IndexError, ValueError) as exc:
            raise InputError(f"{source}: corrupt {source.name} (a field holds a value of the wrong kind: "
                             f"{exc})") from None
        title = f"hsicam {kind} report"
        page = (f"<!doctype html><html><head><meta charset='utf-8'><title>{title}</title><style>{CSS}</style></head>"
                f"<body><h1>{title}</h1><p class='note'>{html.escape(str(folder))}</p>{''.join(body)}{CHECK_IMAGES}</body></html>")
        with atomic_open(out / "index.html", "w", encoding="utf-8") as fh:
            fh.write(page)
    return folder / "report" / "index.html"


def _read_json(path: Path) -> dict:
    try:
        data = json.loads(path.read_text(encoding="utf-8-sig"))  # (a byte-order mark, as some editors save: read)
    except UnicodeDecodeError:
        raise InputError(f"{path}: corrupt {path.name} (not UTF-8 text)") from None
    except json.JSONDecodeError as exc:
        raise InputError(f"{path}: corrupt {path.name} ({exc.msg} at line {exc.lineno})") from None
    if not isinstance(data, dict):
        raise InputError(f"{path}: corrupt {path.name} (not a JSON object)")
    return nan_for_null(data)  # a score written as null (not finite: an undefined SAM) is NaN again


_FIELDS = {"evaluation": {"scenes": list, "mean": dict, "conventions": dict},
           "experiment": {"experiment": str, "scale": str, "scenes": list, "rows": list, "conventions": dict}}


def _check_fields(path: Path, data: dict, kind: str) -> None:
    """One-line InputError naming the first field the report reads that is missing or of the wrong kind."""
    def corrupt(what: str) -> InputError:
        return InputError(f"{path}: corrupt {path.name} ({what})")

    for key, typ in _FIELDS[kind].items():
        if not isinstance(data.get(key), typ):
            raise corrupt(f"'{key}' is missing or not a {typ.__name__}")
    rows = data["scenes"] if kind == "evaluation" else data["rows"]
    if not all(isinstance(r, dict) for r in rows):
        raise corrupt(f"an entry of '{'scenes' if kind == 'evaluation' else 'rows'}' is not an object")
    if kind == "evaluation":
        if "bands_nm" in data and not _numbers(data["bands_nm"], positive=True):
            raise corrupt("'bands_nm' is not a list of wavelengths in nm")
        if "bands_nm" in data and any(b <= a for a, b in zip(data["bands_nm"], data["bands_nm"][1:])):
            raise corrupt("'bands_nm' is not in strictly ascending order")
        held = data.get("heldout")
        if isinstance(held, dict) and held.get("scenes"):
            if not isinstance(held["scenes"], list) or not all(isinstance(r, dict) for r in held["scenes"]):
                raise corrupt("'heldout.scenes' is not a list of objects")
            if not isinstance(held.get("mean"), dict):
                raise corrupt("'heldout.mean' is missing or not a dict")
        return
    if "seeds" not in data:
        raise corrupt("'seeds' is missing")
    figures = data.get("figures", [])
    if not (isinstance(figures, list) and all(
            isinstance(f, dict) and isinstance(f.get("file"), str) and Path(f["file"]).name == f["file"]
            and isinstance(f.get("scene"), str) and isinstance(f.get("role"), str)
            and isinstance(f.get("methods"), list) and f["methods"] for f in figures)):
        raise corrupt("'figures' is not a list of objects naming a file of the folder, its scene, role and methods")
    if not all(isinstance(r.get("method"), str) for r in rows):
        raise corrupt("an entry of 'rows' names no 'method'")
    if data["experiment"] == "noise":
        grid = data.get("noise_grid")
        if not isinstance(grid, dict):
            raise corrupt("'noise_grid' is missing")
        if not _numbers(grid.get("sigma_height_nm")):
            raise corrupt("'noise_grid.sigma_height_nm' is not a list of numbers")
        results = grid.get("results")
        point = ("sigma_height_nm", "sensor_sigma", "psnr", "ssim")
        def numeric(g) -> bool:
            return isinstance(g, dict) and _numbers([g.get(k) for k in point], finite=False)

        if not isinstance(results, dict) or not all(isinstance(pts, list) and all(map(numeric, pts))
                                                    for pts in results.values()):
            raise corrupt("'noise_grid.results' is not, per camera, a list of points with numeric "
                          + ", ".join(point))


def _numbers(values, positive: bool = False, finite: bool = True) -> bool:
    """Whether ``values`` is a non-empty list of JSON numbers, finite unless ``finite=False`` (a score may be
    NaN or infinite), and > 0 with ``positive``."""
    return (isinstance(values, list) and bool(values)
            and all(json_number(v, finite) and (v > 0 or not positive) for v in values))


# -- sections ---------------------------------------------------------------------------------
def _img(name: str, caption: str) -> str:
    """A figure of the image file ``name`` (a path relative to the page: percent-encoded, so that a scene's
    ``#``, ``?`` or ``%`` is part of the file name, not a fragment, a query or an escape)."""
    return (f"<figure><img src='{html.escape(urllib.parse.quote(name))}' alt='{html.escape(caption)}'>"
            f"<figcaption class='note'>{html.escape(caption)}</figcaption></figure>")


#: The scenes whose reconstructions an evaluation's report draws (the first by name; a note says how many were saved).
MAX_RECONSTRUCTIONS = 6


def _cell(v, fmt: str) -> str:
    """A table cell's text: a number in ``fmt``; "n/a" for a score that has no value (null, NaN: e.g. the SAM of
    a scene whose truth is zero at every scored pixel); "inf" / "-inf" for an infinite one (the best or the worst
    score, e.g. the -inf dB of a broken estimate: it has a value, and a mean over it is that infinity)."""
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return "n/a"
    if isinstance(v, float) and math.isinf(v):
        return "inf" if v > 0 else "-inf"
    if isinstance(v, bool):  # an edited file's true/false: not a score of 1.00 / 0.00
        return str(v).lower()
    return format(v, fmt) if isinstance(v, (int, float)) and fmt else str(v)


def _table(rows: list[dict], cols: list[tuple[str, str, str]]) -> str:
    """cols: (key, header, format). A column that no row has is left out (results of an older hsicam record fewer
    scores); a score one row lacks is "n/a" (an edited file), not an empty cell."""
    cols = [c for i, c in enumerate(cols) if i == 0 or any(c[0] in r for r in rows)]
    head = "".join(f"<th>{html.escape(h)}</th>" for _, h, _ in cols)
    body = []
    for r in rows:
        cells = []
        for i, (key, _, fmt) in enumerate(cols):
            cells.append(f"<td>{html.escape(_cell(r.get(key, '' if i == 0 else None), fmt))}</td>")
        body.append("<tr>" + "".join(cells) + "</tr>")
    return f"<table><tr>{head}</tr>{''.join(body)}</table>"


def _conventions(conv: dict) -> str:
    return "<p class='note'>" + "; ".join(f"{html.escape(k)}: {html.escape(str(v))}" for k, v in conv.items()) + "</p>"


def _camera_section(run: Path, out: Path, prefix: str = "", label: str | None = None,
                    scored_sha256: str | None = None, rescore: str = "evaluate it again") -> str:
    """The camera figures of the run folder ``run`` (or ``pretrained:NAME``), headed by ``label``, by
    default its :func:`hsicam.runs.pretrained.run_label` (a shipped camera by its name, not its
    package folder). ``scored_sha256``: the weights the results were scored with (results.json's
    ``weights_sha256``): when the run's weights are others now (trained on, or replaced), its camera is
    not the one scored, and a note says so instead of figures (they were drawn beside the old scores), with
    ``rescore``, what scores it again."""
    from hsicam.runs.checkpoint import root_weights_path
    from hsicam.io import file_sha256
    from hsicam.runs.folder import load_run
    from hsicam.runs.pretrained import resolve_run, run_label
    from hsicam.report.camera import write_optics_figures

    try:
        cfg, model = load_run(run)
        run = resolve_run(run)
        now = file_sha256(root_weights_path(run)) if scored_sha256 else None
    except (InputError, ConfigError) as exc:  # (a run's damaged config.yaml: the run's, not the results file's fault)
        return f"<p class='note'>camera figures unavailable: {html.escape(str(exc))}</p>"
    if scored_sha256 and now != scored_sha256:
        return (f"<p class='note'>camera figures left out: the weights of {html.escape(label or run_label(run))} "
                f"changed since these results were scored (sha256 {html.escape(scored_sha256[:12])}… then, "
                f"{html.escape(str(now)[:12])}… now: trained on, or replaced), so its camera now is not the one "
                f"scored; {html.escape(rescore)} for its current camera</p>")
    cam = model.camera
    parts = [f"<h2>Camera ({html.escape(label or run_label(run))})</h2>"]
    try:
        figures = write_optics_figures(cam, out, prefix, psf=True)
    except InputError as exc:  # the run's camera (its weights or config.yaml), not the results file: say which
        figures = {}
        parts.append(f"<p class='note'>camera figures unavailable: {html.escape(str(run))}: the camera its weights and "
                     f"config.yaml describe cannot be drawn ({html.escape(str(exc))}): the run's model.safetensors or "
                     f"config.yaml is damaged</p>")
    for name, caption in figures.items():
        parts.append(_img(name, caption))
    metrics = run / "metrics.jsonl"
    if metrics.is_file():
        try:
            plot_training_curves(metrics, out / f"{prefix}training.png", cfg.train.loss_formula())
        except (ValueError, KeyError, TypeError) as exc:  # the run's log (a bad line, bad UTF-8), not the results file
            parts.append(f"<p class='note'>training curves unavailable: {html.escape(str(metrics))} is damaged "
                         f"({html.escape(type(exc).__name__)}: {html.escape(str(exc))})</p>")
        else:
            parts.append(_img(f"{prefix}training.png", "training loss and the PSNR / SSIM on validation patches"))
    return "".join(parts)


def _evaluation_sections(folder: Path, out: Path, res: dict) -> list[str]:
    # the facts the results record (a demo folder of an older hsicam records fewer: no empty "data: ; noise: null")
    facts = [f"{label}{html.escape(text)}" for label, text in (
        ("data: ", str(res["data"]) if res.get("data") else None),
        ("noise: ", json.dumps(res["noise"]) if res.get("noise") is not None else None),
        ("config ", str(res["config_hash"]) if res.get("config_hash") else None),
        ("scored area: ", str(res["region"]) if res.get("region") else None),
        ("", str(res["warning"]) if res.get("warning") else None),  # scenes the run trained on
        ("", str(res["truth_interpolated"]) if res.get("truth_interpolated") else None)) if text is not None]
    method = f": {html.escape(str(res['method']))}" if res.get("method") else ""
    parts = [f"<h2>Results{method}</h2>"] + ([f"<p class='note'>{'; '.join(facts)}</p>"] if facts else [])
    cols = [("name", "scene", ""), ("psnr", "PSNR (dB)", ".2f"), ("ssim", "SSIM", ".4f"), ("sam", "SAM (°)", ".2f"),
            ("ergas", "ERGAS", ".2f"), ("psnr_mst", "PSNR MST (dB)", ".2f"), ("runtime_s", "runtime (s)", ".3f")]
    parts.append(_table(res["scenes"] + [{"name": "mean", **res["mean"]}], cols))
    if not res["scenes"]:  # (an edited file: an evaluation writes a row per scene it scored)
        parts.append("<p class='note'>results.json lists no scene: the mean above is the file's own, over no row "
                     "shown here</p>")
    if isinstance(res.get("weights"), dict):  # which checkpoint was scored (evaluate and demo record it)
        from hsicam.runs.checkpoint import weights_text

        try:
            parts.append(f"<p class='note'>{html.escape(weights_text(res['weights']))}</p>")
        except (KeyError, TypeError):  # a results.json from elsewhere: its fields are not ours to vouch for
            pass
    parts += _references(res)
    parts.append(_conventions(res["conventions"]))
    held = res.get("heldout")
    if isinstance(held, dict) and held.get("scenes"):  # scored beside the validation scenes (evaluate on synthetic data)
        parts.append("<h2>Held-out spectral sources</h2>")
        parts.append(f"<p class='note'>{html.escape(str(held.get('data', '')))}</p>")
        parts.append(_table(held["scenes"] + [{"name": "mean", **held["mean"]}], cols))
        parts += _references(held)
    if (folder / "reconstructions.png").is_file():  # hsicam demo's own figure, beside its results.json
        parts.append(_img("../reconstructions.png", "the demo's reconstructions (hsicam demo), as written beside "
                                                    "its results.json"))
    cubes = folder / "cubes"
    if not cubes.is_dir() and not (folder / "reconstructions.png").is_file():  # said, not silently left out
        parts.append("<h2>Reconstructions</h2><p class='note'>None shown: the evaluation saved no cubes (run "
                     "<code>hsicam evaluate … --save</code> for renders, spectra and per-band errors).</p>")
    if cubes.is_dir():  # (each cube carries its own bands: results.json's bands_nm is not needed)
        from hsicam.data import read_cube

        parts.append("<h2>Reconstructions</h2>")
        saved = {p.name[: -len("_estimate.h5")]: p for p in sorted(cubes.glob("*_estimate.h5"))}  # scene → estimate
        paired = [name for name in saved if (cubes / f"{name}_truth.h5").is_file()]
        unpaired = [saved[name].name for name in saved if name not in paired]
        shown = paired[:MAX_RECONSTRUCTIONS]
        notes = []
        if len(paired) > len(shown):
            notes.append(f"the first {len(shown)} by name of the {len(paired)} scenes saved with their ground truth "
                         "(each scene's cubes are in cubes/)")
        if unpaired:
            notes.append(f"not shown, their ground truth missing from cubes/: {', '.join(unpaired)}")
        if not saved:
            notes.append("cubes/ holds no reconstruction (*_estimate.h5)")
        if notes:
            parts.append(f"<p class='note'>{html.escape('; '.join(notes))}</p>")
        for name in shown:
            est_path, truth_path = saved[name], cubes / f"{name}_truth.h5"
            est, b, _ = read_cube(est_path)
            truth, tb, _ = read_cube(truth_path)
            if truth.shape != est.shape or not tb.matches(b):
                raise InputError(f"{truth_path}: a {_cube_text(truth, tb)} cube, but {est_path.name} holds a "
                                 f"{_cube_text(est, b)} one: not the same scene's pair (cubes/ of two evaluations?)")
            plot_scene_comparison(truth, est, b, out / f"recon_{name}.png", title=name)
            plot_band_errors(truth, est, b, out / f"errors_{name}.png", title=name)
            parts.append(_img(f"recon_{name}.png", f"{name}: ground truth vs reconstruction (sRGB, CIE 1931 / D65) with zoomed crops and spectra at marked pixels"))
            parts.append(_img(f"errors_{name}.png", f"{name}: absolute error per band"))
    if res.get("run"):
        sha = res.get("weights_sha256")
        parts.append(_camera_section(_evaluated_run(res, folder), out, label=str(res["run"]),
                                     scored_sha256=sha if isinstance(sha, str) else None))
    return parts


def _cube_text(cube: np.ndarray, bands: Bands) -> str:
    """``C-band (A-B nm) H×W``: a cube and its bands, for a message."""
    return f"{len(bands)}-band ({bands.centers_nm[0]:g}-{bands.centers_nm[-1]:g} nm) {cube.shape[1]}×{cube.shape[2]}"


def _references(res: dict) -> list[str]:
    """The network-free references scored beside the camera (``hsicam demo``'s ``references``) as a table."""
    refs = [r for r in res.get("references") or () if isinstance(r, dict) and isinstance(r.get("mean"), dict)]
    if not refs:
        return []
    cols = [("name", "reference", ""), ("psnr", "PSNR (dB)", ".2f"), ("ssim", "SSIM", ".4f"), ("sam", "SAM (°)", ".2f")]
    return ["<p class='note'>references on the same scenes:</p>",
            _table([{"name": str(r.get("method", "")), **r["mean"]} for r in refs], cols)]


def _evaluated_run(res: dict, folder: Path) -> Path:
    """Where the run an evaluation scored is read from: ``run_path``, the folder ``hsicam evaluate``
    read (``run`` is its label: ``pretrained:NAME`` for a shipped camera), when it is still there; else
    ``run`` (a results.json from before run_path, or from another machine: a run folder, or
    ``pretrained:NAME``, which :func:`hsicam.runs.folder.load_run` finds among this installation's cameras); else,
    a relative ``run``, the results ``folder``'s own sub-folder of its name (the demo's layout, DIR/results.json
    beside DIR/run, copied or moved elsewhere: its camera figures were all left out). Of those that exist, the first
    whose weights are the ones the results record (``weights_sha256``): an archived demo's report read the new run
    at the old place before the scored one beside it (session 74's review); else the first, whose camera
    :func:`_camera_section` then leaves out, saying why."""
    from hsicam.runs.checkpoint import root_weights_path
    from hsicam.io import file_sha256

    run = Path(str(res["run"]))
    path = res.get("run_path")
    candidates = [Path(path)] if isinstance(path, str) and path else []
    candidates.append(run)
    if not run.is_absolute() and not str(run).startswith("pretrained:"):
        candidates.append(folder / run.name)
    found = [c for c in candidates if c.is_dir()]
    sha = res.get("weights_sha256")
    for c in found if isinstance(sha, str) else ():
        try:
            if file_sha256(root_weights_path(c)) == sha:
                return c
        except (InputError, OSError):  # not a run folder with weights: another candidate may be
            continue
    return found[0] if found else run


def _experiment_sections(folder: Path, out: Path, exp: dict) -> list[str]:
    parts = [f"<h2>Experiment: {html.escape(exp['experiment'])} ({html.escape(exp['scale'])} scale)</h2>",
             f"<p class='note'>{len(exp['scenes'])} validation scenes, seeds {html.escape(str(exp['seeds']))}"
             + (f"; scored area: the DOE cameras' {html.escape(str(exp['region']))}"
                + (", the CASSI rows' too" if exp["experiment"] == "compare" else "") if exp.get("region") else "")
             + "</p>"]
    rows = [r for r in exp["rows"] if "missing" not in r]
    if exp["experiment"] == "noise":
        cols = [("method", "camera", ""), ("psnr", "PSNR clean", ".2f"), ("ssim", "SSIM clean", ".4f"),
                ("psnr_worst", "worst PSNR", ".2f"), ("ssim_worst", "worst SSIM", ".4f")]
        parts.append(_table(rows, cols))
        plot_noise_grid(exp["noise_grid"], out / "noise_grid.png")
        parts.append(_img("noise_grid.png", "PSNR (solid) and SSIM (dashed) versus sensor noise σ_s, one colour per DOE height noise σ_p"))
    else:
        cols = [("method", "method", ""), ("psnr", "PSNR (dB)", ".2f"), ("ssim", "SSIM", ".4f"), ("sam", "SAM (°)", ".2f"),
                ("runtime_s", "runtime (s/scene)", ".3f")]
        parts.append(_table(rows, cols))
        if exp["experiment"] == "cfa-period" and plot_period_sweep(rows, out / "period_sweep.png"):
            parts.append(_img("period_sweep.png", "PSNR, SSIM and SAM versus the CFA period (the paper's sweep: its "
                                                  "9×9 best of 3–15), one camera trained per period"))
        missing = [r["method"] for r in exp["rows"] if "missing" in r]
        if missing:
            parts.append(f"<p class='note'>not available in this installation: {html.escape(', '.join(missing))}</p>")
        gone = [str(f["file"]) for f in exp.get("figures") or () if not (folder / f["file"]).is_file()]
        if gone:  # listed, but not beside experiment.json (moved or deleted): said, not silently left out
            parts.append(f"<p class='note'>figures listed in experiment.json but missing from the folder: "
                         f"{html.escape(', '.join(gone))}</p>")
        for f in exp.get("figures") or ():  # drawn by the experiment beside its experiment.json (the arrays are not kept)
            if (folder / f["file"]).is_file():
                parts.append(_img(f"../{f['file']}", f"{f['scene']} ({f['role']} scene of {f['methods'][0]} by PSNR): "
                                  "ground truth and each method's reconstruction (absolute sRGB render, CIE 1931 / D65, "
                                  "not exposed per image), titled with its PSNR / SSIM on this scene, and each "
                                  "method's mean |error| over bands on one colour scale"))
    parts.append(_conventions(exp["conventions"]))
    runs = [p for p in (folder / "runs").iterdir() if (p / "model.safetensors").is_file()] if (folder / "runs").is_dir() else []
    # in the table's order where a run is a row's, then by name with its numbers as numbers (period-3 before period-12)
    order = {str(r.get("method")): i for i, r in enumerate(exp["rows"])}
    runs.sort(key=lambda p: (order.get(p.name, len(order)), _natural_key(p.name)))
    # the weights each run's row was scored with (experiment.json from session 74 on): a run trained on or replaced
    # since is not drawn beside the old row (an older experiment.json records none: the camera now is drawn)
    scored = {str(r.get("method")): r["weights_sha256"] for r in exp["rows"] if isinstance(r.get("weights_sha256"), str)}
    for i, run in enumerate(runs):
        parts.append(_camera_section(run, out, prefix=f"{i:02d}_", label=f"runs/{run.name}",
                                     scored_sha256=scored.get(run.name),
                                     rescore=f"score it as it is now with `hsicam evaluate --run {run}`, or delete it and "
                                             f"run `hsicam experiment {exp['experiment']}` into this folder again (a "
                                             "run trained on since is not the experiment's and is refused)"))
    return parts


def _natural_key(name: str) -> list:
    """A sort key that orders the numbers within ``name`` by value: period-3, period-12."""
    return [(0, int(t), "") if t.isdigit() else (1, 0, t) for t in re.split(r"(\d+)", name) if t]


# -- figures ------------------------------------------------------------------------------------
def plot_scene_comparison(truth: np.ndarray, est: np.ndarray, bands: Bands, path: Path, title: str = "") -> None:
    """Ground truth and reconstruction in sRGB with two zoomed crops each, plus spectra at 3 pixels."""
    gt_rgb, est_rgb = np.clip(cube_rgb(truth, bands), 0, 1), np.clip(cube_rgb(est, bands), 0, 1)
    h, w = truth.shape[1:]
    s = max(min(h, w) // 4, 4)
    crops = [((h - s) // 2, (w - s) // 2, "tab:cyan"), (h // 8, w // 8, "tab:pink")]
    pts = [(h // 4, 3 * w // 4, "tab:red"), (h // 2, w // 2, "tab:green"), (3 * h // 4, w // 4, "tab:blue")]
    fig = Figure(figsize=(13, 6))
    gs = fig.add_gridspec(2, 5)
    for col, (img, name) in enumerate(((gt_rgb, "ground truth"), (est_rgb, "reconstruction"))):
        ax = fig.add_subplot(gs[:, col])
        ax.imshow(img)
        ax.set_title(f"{title} {name}", fontsize=9)
        for y, x, c in crops:
            ax.add_patch(Rectangle((x, y), s, s, fill=False, ec=c, lw=1.5))
        for y, x, c in pts:
            ax.plot(x, y, "o", mfc="none", mec=c, ms=7)
        ax.set_xticks([])
        ax.set_yticks([])
        for row, (y, x, c) in enumerate(crops):
            cax = fig.add_subplot(gs[row, 2 + col])
            cax.imshow(img[y : y + s, x : x + s], interpolation="nearest")
            cax.set_title(f"{name} crop", fontsize=8, color=c)
            cax.set_xticks([])
            cax.set_yticks([])
    ax = fig.add_subplot(gs[:, 4])
    exp = spectra_exponent([a[:, y, x] for y, x, _ in pts for a in (truth, est)])
    for y, x, c in pts:
        ax.plot(bands.centers_nm, truth[:, y, x] / 10.0**exp, color=c, lw=1.6)
        ax.plot(bands.centers_nm, est[:, y, x] / 10.0**exp, color=c, lw=1.2, ls="--")
    ax.yaxis.tick_right()  # clear of the crop beside it (the labels ran over it)
    ax.yaxis.set_label_position("right")
    ax.set_ylabel("value (peak 1)" + (f", × 1e{exp}" if exp else ""), fontsize=8)
    ax.set_xlabel("wavelength (nm)")
    ax.set_title("spectra: truth solid, reconstruction dashed", fontsize=8)
    save_figure(fig, path)


def plot_band_errors(truth: np.ndarray, est: np.ndarray, bands: Bands, path: Path, max_bands: int = 16,
                     title: str = "") -> None:
    """|estimate − truth| for up to ``max_bands`` evenly chosen bands, one shared colour scale up to the 99.5th
    percentile of the shown errors; when larger errors are clipped, the colour bar's arrow and the title say so,
    with the largest error."""
    idx = np.unique(np.linspace(0, len(bands) - 1, min(max_bands, len(bands))).round().astype(int))
    err = np.abs(est - truth)
    vmax = max(float(np.percentile(err[idx], 99.5)), 1e-6)
    top = float(err[idx].max())
    cols = min(8, idx.size)
    rows = int(np.ceil(idx.size / cols))
    fig = Figure(figsize=(1.7 * cols, 1.9 * rows))
    axes = fig.subplots(rows, cols, squeeze=False)
    for ax in axes.flat:
        ax.axis("off")
    for ax, i in zip(axes.flat, idx):
        im = ax.imshow(err[i], cmap="magma", vmin=0, vmax=vmax)
        ax.set_title(f"{bands.centers_nm[i]:g} nm", fontsize=8)
    clipped = top > vmax
    fig.colorbar(im, ax=axes.ravel().tolist(), fraction=0.02, label="|error|", extend="max" if clipped else "neither")
    fig.suptitle(f"{title + ': ' if title else ''}|reconstruction − truth| per band, one colour scale"
                 + (f"; errors above {vmax:.3g} (the top 0.5 %) clipped, up to {top:.3g}" if clipped else ""), fontsize=9)
    save_figure(fig, path)


def plot_period_sweep(rows: list[dict], path: Path) -> bool:
    """The CFA-period sweep's figure: PSNR, SSIM and SAM of each ``period-m`` row against m, three panels sharing the
    period axis; False (nothing drawn) when fewer than two rows name a period."""
    pts = sorted((int(m.group(1)), r) for r in rows
                 if (m := re.fullmatch(r"period-(\d+)", str(r.get("method", "")))) is not None)
    if len(pts) < 2:
        return False
    periods = [p for p, _ in pts]
    fig = Figure(figsize=(11, 3.4), layout="constrained")
    axes = fig.subplots(1, 3)
    for ax, (key, label) in zip(axes, (("psnr", "PSNR (dB)"), ("ssim", "SSIM"), ("sam", "SAM (°), lower is better"))):
        ax.plot(periods, [float(r[key]) if isinstance(r.get(key), (int, float)) else np.nan for _, r in pts], "-o")
        ax.set_xticks(periods)
        ax.set_xlabel("CFA period m (an m×m tile of m² filters)")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    fig.suptitle("CFA period sweep: one camera trained per period, the same validation scenes", fontsize=9)
    save_figure(fig, path)
    return True


def plot_noise_grid(grid: dict, path: Path) -> None:
    """Fig. 7 style: PSNR (solid, left axis) and SSIM (dashed, right axis) versus σ_s per σ_p, one panel per
    camera, every panel on the same PSNR and the same SSIM scale (the cameras are compared across panels)."""
    names = list(grid["results"])
    # constrained: a panel's SSIM axis is clear of the next one's PSNR axis
    fig = Figure(figsize=(5.5 * len(names), 4), layout="constrained")
    axes = fig.subplots(1, len(names), squeeze=False, sharey=True)
    colors = matplotlib.colormaps["viridis"](np.linspace(0, 0.9, len(grid["sigma_height_nm"])))
    first_ssim = None
    for ax, name in zip(axes[0], names):
        ax2 = ax.twinx()
        if first_ssim is None:
            first_ssim = ax2
        else:
            ax2.sharey(first_ssim)
        for sp, c in zip(grid["sigma_height_nm"], colors):
            pts = [g for g in grid["results"][name] if g["sigma_height_nm"] == sp]
            xs = [g["sensor_sigma"] for g in pts]
            ax.plot(xs, [g["psnr"] for g in pts], "-o", color=c, label=f"σ_p {sp:g} nm")
            ax2.plot(xs, [g["ssim"] for g in pts], "--s", color=c, ms=4)
        ax.set_xlabel("sensor noise σ_s (fraction of full scale)")
        ax.set_ylabel("PSNR (dB), solid")
        ax.yaxis.set_tick_params(labelleft=True)  # sharey hides them on all but the first panel
        ax2.set_ylabel("SSIM, dashed")
        ax.set_title(name)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    save_figure(fig, path)
