"""Every ```python block that README.md, docs/ and the shipped cameras' cards show a user is either
run or checked against the code (the Python counterpart of ``test_documented_commands.py``).

The blocks are found by globbing the documents, and each must be registered here as one of:

- :class:`Run`: a runnable example, executed as written (compiled with the document's own file name
  and line numbers, so a traceback points at the document). The names the prose leaves to the reader
  (``scene``, ``sensor``) are the only free names allowed, and the test supplies them as real tensors
  of the shape the example's comment documents (``# scene (B, 31, H+140, W+140) -> sensor (B, 1, H,
  W)`` makes ``scene`` of that shape, ``B``, ``H``, ``W`` small). Each shape in a comment, ``(a,
  b, …)`` (of the assigned name, or ``name (…) -> (…)``: of the input ``name``, then of the assigned
  name), is asserted, and so is a tuple of type names (``# (config, CameraSystem)``). The prose's other
  claims are checked by the entry's ``check``.
- :class:`Listing`: a list of signatures (``f(a, b=1, *, c=X) -> T``, not Python), one entry per
  bracket-balanced line group, each checked against :func:`inspect.signature` of the function in the
  named module: parameter names in order, positional / keyword-only marks, the defaults written
  (``...``: elided; a name: that constant of the module), a written return annotation; an entry written
  as a call (``parse_holdout("a,b")``) must bind. Upper-case names (``UNSEEN_LAYOUTS``) and ``*.py``
  paths in its comments must exist. Not run.
- :class:`Skeleton`: a code outline with ``...`` bodies, parsed with :mod:`ast`, never executed: its
  imports resolve; each class and function it defines exists in the implied module (the one the prose
  names as the example); a class's bases are real bases, its attributes hold the written values, its
  methods exist with the written decorators (``classmethod``, ``property``) and signatures, and match
  the signature of an imported base that declares them (``Camera.A``); registry decorators bind to the
  real decorator's signature and the registry holds what they say (:data:`REGISTRIES`); every other name
  used resolves.

- :class:`Excerpt`: lines quoted from a file of the checkout (``examples/*.py``, which ``test_examples.py``
  runs): each non-blank line of the block is, stripped of its indentation, a line of that file, in the file's
  order, so the page cannot drift from the code it quotes. Not run.

A block that is none of these fails unless :data:`NOT_CHECKED` lists it with a reason.
"""

from __future__ import annotations

import ast
import builtins
import dataclasses
import importlib
import inspect
import io
import re
import textwrap
import tokenize
from pathlib import Path
from typing import Any, Callable

import h5py
import numpy as np
import pytest
import torch

ROOT = Path(__file__).resolve().parents[2]
#: The documents: README, docs/, and the Markdown shipped in the package (the pretrained cameras' cards).
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").rglob("*.md")), *sorted((ROOT / "src" / "hsicam").rglob("*.md"))]
_PY_FENCES = {"python", "py", "python3", "pycon"}


@dataclasses.dataclass(frozen=True)
class Block:
    """A ```python block: its document, the document line of its first code line, its code (dedented)."""

    file: str
    line: int
    code: str

    @property
    def first(self) -> str:
        """Its first non-blank code line (how the registries below name it)."""
        return next((ln.strip() for ln in self.code.splitlines() if ln.strip()), "")

    def padded(self) -> str:
        """Its code preceded by blank lines, so that line numbers are the document's."""
        return "\n" * (self.line - 1) + self.code

    def __str__(self) -> str:
        return f"{self.file}:{self.line}"


def python_blocks(path: Path, root: Path = ROOT) -> list[Block]:
    """The ```python blocks of the Markdown file ``path``."""
    name = path.relative_to(root).as_posix()
    out: list[Block] = []
    fence, start, lines = None, 0, []
    for no, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
        stripped = line.strip()
        if not stripped.startswith("```"):
            lines.append(line)
            continue
        if fence is None:
            fence, start, lines = (stripped[3:].strip().split() or [""])[0].lower(), no + 1, []
        else:
            if fence in _PY_FENCES:
                out.append(Block(name, start, textwrap.dedent("\n".join(lines)) + "\n"))
            fence = None
    return out


def all_blocks() -> list[Block]:
    return [b for doc in DOCS for b in python_blocks(doc)]


# --------------------------------------------------------------------------- what each block is


@dataclasses.dataclass(frozen=True)
class Run:
    """A runnable example. ``given``: the names the prose leaves to the reader, made by the test: a
    tensor of the shape the example's comment gives that name (values in [0, 1)); ``symbols``: the sizes
    its shapes use (a value, or a function of the example's names after it ran: ``C``); ``prepare(tmp_path)``
    runs first, in ``tmp_path`` as working directory (files the example reads); ``check(names)`` checks
    what the prose claims beyond the comments' shapes."""

    given: tuple[str, ...] = ()
    symbols: dict[str, Any] = dataclasses.field(default_factory=dict)
    prepare: Callable[[Path], None] | None = None
    check: Callable[[dict[str, Any]], None] | None = None


@dataclasses.dataclass(frozen=True)
class Listing:
    """A list of signatures of functions of ``module`` (see the module docstring)."""

    module: str


@dataclasses.dataclass(frozen=True)
class Skeleton:
    """A code outline whose classes and functions live in ``module`` (see the module docstring)."""

    module: str


@dataclasses.dataclass(frozen=True)
class Excerpt:
    """Lines quoted from the file ``path`` (relative to the checkout's root; see the module docstring)."""

    path: str


def check_excerpt(block: Block, path: str) -> list[str]:
    """The block's non-blank lines that are not lines of ``path`` (stripped), or not in the file's order."""
    lines = [ln.strip() for ln in (ROOT / path).read_text(encoding="utf-8").splitlines()]
    problems, at = [], 0
    for no, line in enumerate(block.code.splitlines(), block.line):
        if not line.strip():
            continue
        if line.strip() not in lines:
            problems.append(f"{block.file}:{no}: {line.strip()!r} is not a line of {path}")
        elif line.strip() not in lines[at:]:
            problems.append(f"{block.file}:{no}: {line.strip()!r} comes before the line above it in {path}")
        else:
            at = lines.index(line.strip(), at) + 1
    return problems


# -- the runnable examples' data and claims


def _check_camera_example(ns: dict[str, Any]) -> None:
    """README: the PSF is an energy fraction per pixel, ``cam(scene)`` is ``noise(cam.A(scene))`` and
    ``cam.A_adjoint`` is the adjoint of ``cam.A``: <A s, y> = <s, Aᵀ y>."""
    cam, scene, psf, g = ns["cam"], ns["scene"], ns["psf"].detach(), ns["g"].detach()
    assert float(psf.min()) >= 0 and float(psf.sum(dim=(-2, -1)).max()) <= 1 + 1e-5, "psf: not an energy fraction"
    with torch.no_grad():
        # the preset's noise is off, so g is A(scene) (else computed: each call of A builds the PSFs, seconds)
        a = g if all(v == 0 for v in cam.noise_levels().values()) else cam.A(scene)
        sigma = 0.05
        cam.set_noise(sensor_sigma=sigma)  # "noise included": the camera's noise on A(scene)
        y = cam(scene, torch.Generator().manual_seed(0))
        assert float((y - a).std()) == pytest.approx(sigma, rel=0.1), "cam(scene) is not noise(A(scene))"
        x = cam.A_adjoint(y)
    assert ns["x"].shape == scene.shape, "A_adjoint: not back to the scene's shape"
    lhs, rhs = float((a.double() * y.double()).sum()), float((scene.double() * x.double()).sum())
    assert lhs == pytest.approx(rhs, rel=1e-4), f"<A s, y> = {lhs} but <s, A^T y> = {rhs}"


#: The ICVL cube data.md's read_cube example reads: MATLAB's (H, W, C), bands 400–700 nm.
_ICVL_HWC = (np.random.default_rng(0).random((5, 7, 31)) + 0.01).astype(np.float32)
_ICVL_NM = np.arange(400.0, 701.0, 10.0)


def _write_mat73(path: Path, variables: dict[str, np.ndarray]) -> None:
    """A MATLAB v7.3 MAT-file as MATLAB writes it (as in test_data_formats.py): HDF5 with a 512-byte MAT
    header in the user block, column-major arrays (h5py sees an H×W×C array as (C, W, H))."""
    with h5py.File(path, "w", userblock_size=512) as f:
        for name, value in variables.items():
            ds = f.create_dataset(name, data=np.ascontiguousarray(np.asarray(value).T))
            ds.attrs["MATLAB_class"] = np.bytes_("double" if value.dtype == np.float64 else "single")
    text = b"MATLAB 7.3 MAT-file, Platform: GLNXA64, Created on: Mon Jan  1 00:00:00 2024 HDF5 schema 1.00 ."
    with open(path, "r+b") as fh:
        fh.write((text.ljust(116, b" ") + b"\x00" * 8 + b"\x00\x02" + b"IM").ljust(512, b"\x00"))


def _prepare_icvl(tmp_path: Path) -> None:
    _write_mat73(tmp_path / "BGU_0403-1419-1.mat", {"rad": _ICVL_HWC, "bands": _ICVL_NM[None, :]})


def _check_read_cube_example(ns: dict[str, Any]) -> None:
    """data.md: a cube is float32 (C, H, W), bands ascending, paired with its Bands; the ICVL format is
    told by the content (the variable ``rad`` in a MAT v7.3 file)."""
    from hsicam.spectral import Bands

    cube, bands, meta = ns["cube"], ns["bands"], ns["meta"]
    assert cube.dtype == np.float32 and cube.shape == (31, 5, 7)
    np.testing.assert_allclose(cube, _ICVL_HWC.transpose(2, 0, 1))
    assert isinstance(bands, Bands) and list(bands.centers_nm) == pytest.approx(list(_ICVL_NM))
    assert meta["format"] == "icvl"


def _check_pretrained_example(ns: dict[str, Any]) -> None:
    """pretrained.md: the shipped camera is available and reconstructs a finite float32 cube on its bands."""
    cube = ns["cube"]
    assert "standard" in ns["available"]() and ns["summary"]("standard")
    assert ns["resolve_run"]("pretrained:standard") == ns["pretrained_dir"]("standard")
    assert cube.dtype == torch.float32 and bool(torch.isfinite(cube).all())


#: Each block, by (document, start of its first code line) → how it is run or checked.
BLOCKS: dict[tuple[str, str], Run | Listing | Skeleton | Excerpt] = {
    ("README.md", "from hsicam.config import load_config"):
        Run(given=("scene",), symbols={"B": 2, "H": 12, "W": 20}, check=_check_camera_example),
    ("docs/data.md", "from hsicam.data import read_cube"):
        Run(prepare=_prepare_icvl, check=_check_read_cube_example),
    ("docs/data.md", "synthetic_dataset("): Listing("hsicam.data.synthetic"),
    ("docs/pretrained.md", "from hsicam.runs.folder import load_run"):
        Run(given=("sensor",), symbols={"B": 2, "H": 24, "W": 28, "C": lambda ns: len(ns["system"].bands)},
            check=_check_pretrained_example),
    ("docs/architecture.md", "from hsicam.cameras.base import Camera"): Skeleton("hsicam.cameras.cassi"),
    ("docs/architecture.md", "from hsicam.models.registry import register_network"): Skeleton("hsicam.models.rdn"),
    ("docs/python.md", "cfg = load_config(\"paper\", [f\"camera.lens.model"): Excerpt("examples/camera_and_psf.py"),
    ("docs/python.md", "cfg, system = load_run(\"pretrained:standard\""): Excerpt("examples/simulate_and_reconstruct.py"),
    ("docs/python.md", "cam = DDCASSICamera.from_config(cfg)"): Excerpt("examples/cassi_baseline.py"),
    ("docs/python.md", "bands = load_config(\"paper\", [\"bands.stop_nm=700\"])"): Excerpt("examples/custom_bands_and_files.py"),
    ("docs/python.md", "cfg = load_config(\"tiny\", [f\"data.cache_dir"): Excerpt("examples/train_tiny.py"),
    ("docs/python.md", "@register_network(\"code_cnn\""): Excerpt("examples/custom_network.py"),
}

#: Blocks neither run nor checked, (document, start of the first code line) → why.
NOT_CHECKED: dict[tuple[str, str], str] = {}


def _entry(block: Block) -> Run | Listing | Skeleton | Excerpt | str | None:
    """What ``block`` is registered as (a :data:`NOT_CHECKED` reason is a str), None when it is not."""
    found = [v for (f, start), v in [*BLOCKS.items(), *NOT_CHECKED.items()]
             if f == block.file and block.first.startswith(start)]
    assert len(found) <= 1, f"{block}: registered more than once"
    return found[0] if found else None


# --------------------------------------------------------------------------- reading Python text


def _comments(code: str) -> dict[int, str]:
    """Line → the text of its ``#`` comment."""
    out: dict[int, str] = {}
    for tok in tokenize.generate_tokens(io.StringIO(code).readline):
        if tok.type == tokenize.COMMENT:
            out[tok.start[0]] = tok.string[1:].strip()
    return out


def _scan(text: str):
    """(index, char, depth) of ``text``'s characters outside string literals, depth being the bracket
    depth before the character."""
    depth, quote = 0, None
    for i, c in enumerate(text):
        if quote:
            quote = None if c == quote else quote
            continue
        if c in "'\"":
            quote = c
            continue
        yield i, c, depth
        depth += 1 if c in "([{" else -1 if c in ")]}" else 0


def _split_arrow(text: str) -> tuple[str, str | None]:
    """``f(a) -> T`` → (``f(a)``, ``T``): split at the top-level ``->``."""
    for i, c, depth in _scan(text):
        if depth == 0 and text.startswith("->", i):
            return text[:i].strip(), text[i + 2:].strip()
    return text.strip(), None


def _strip_comment(line: str) -> tuple[str, str]:
    """(code, comment) of one line."""
    for i, c, _ in _scan(line):
        if c == "#":
            return line[:i].rstrip(), line[i + 1:].strip()
    return line.rstrip(), ""


def _free_names(tree: ast.AST) -> set[str]:
    """Names the code reads but neither assigns, imports, defines nor gets from builtins."""
    bound, used = set(), set()
    for node in ast.walk(tree):
        if isinstance(node, ast.Name):
            (bound if isinstance(node.ctx, (ast.Store, ast.Del)) else used).add(node.id)
        elif isinstance(node, (ast.Import, ast.ImportFrom)):
            bound |= {(a.asname or a.name).split(".")[0] for a in node.names}
        elif isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            bound.add(node.name)
        elif isinstance(node, ast.arg):
            bound.add(node.arg)
    return used - bound - set(dir(builtins))


# --------------------------------------------------------------------------- signatures


def _annotation_text(annotation: Any) -> str:
    """A real annotation as normalised source text (they are strings under ``from __future__ import annotations``)."""
    text = annotation if isinstance(annotation, str) else inspect.formatannotation(annotation)
    try:
        return ast.unparse(ast.parse(text, mode="eval"))
    except SyntaxError:
        return text


def _value(node: ast.expr, namespace: dict[str, Any], what: str) -> Any:
    """The value a written default or argument stands for: a literal, or a name of ``namespace``."""
    try:
        return ast.literal_eval(node)
    except ValueError:
        pass
    if isinstance(node, ast.Name):
        if node.id not in namespace:
            raise LookupError(f"{what} names {node.id}, which does not exist")
        return namespace[node.id]
    if isinstance(node, ast.Attribute):
        owner = _value(node.value, namespace, what)
        if not hasattr(owner, node.attr):
            raise LookupError(f"{what} names {ast.unparse(node)}, which does not exist")
        return getattr(owner, node.attr)
    raise LookupError(f"{what}: cannot tell the value of {ast.unparse(node)}")


_KIND = {
    inspect.Parameter.POSITIONAL_ONLY: "positional-only",
    inspect.Parameter.POSITIONAL_OR_KEYWORD: "positional or keyword",
    inspect.Parameter.VAR_POSITIONAL: "*args",
    inspect.Parameter.KEYWORD_ONLY: "keyword-only",
    inspect.Parameter.VAR_KEYWORD: "**kwargs",
}


def _documented_parameters(args: ast.arguments) -> list[tuple[str, Any, ast.expr | None]]:
    """(name, kind, default node or None) of written parameters, in order."""
    P = inspect.Parameter
    positional = [*args.posonlyargs, *args.args]
    defaults = [None] * (len(positional) - len(args.defaults)) + list(args.defaults)
    out = [(a.arg, P.POSITIONAL_ONLY if i < len(args.posonlyargs) else P.POSITIONAL_OR_KEYWORD, d)
           for i, (a, d) in enumerate(zip(positional, defaults))]
    if args.vararg:
        out.append((args.vararg.arg, P.VAR_POSITIONAL, None))
    out += [(a.arg, P.KEYWORD_ONLY, d) for a, d in zip(args.kwonlyargs, args.kw_defaults)]
    if args.kwarg:
        out.append((args.kwarg.arg, P.VAR_KEYWORD, None))
    return out


def _signature_text(params) -> str:
    """``(a, b, *, c)`` from (name, kind, …) tuples."""
    words, star = [], False
    for name, kind, *_ in params:
        if kind is inspect.Parameter.KEYWORD_ONLY and not star:
            words.append("*")
        star = star or kind in (inspect.Parameter.KEYWORD_ONLY, inspect.Parameter.VAR_POSITIONAL)
        words.append({inspect.Parameter.VAR_POSITIONAL: "*", inspect.Parameter.VAR_KEYWORD: "**"}.get(kind, "") + name)
    return "(" + ", ".join(words) + ")"


def compare_signature(args: ast.arguments, returns: ast.expr | None, real: Callable, where: str, name: str,
                      namespace: dict[str, Any]) -> list[str]:
    """What a written signature gets wrong about ``real``: parameter names and order, kinds, the written
    defaults (``...`` elided), the written return annotation."""
    sig = inspect.signature(real, follow_wrapped=False)
    mine = _documented_parameters(args)
    theirs = [(p.name, p.kind, p.default) for p in sig.parameters.values()]
    problems = []
    if [(n, k) for n, k, _ in mine] != [(n, k) for n, k, _ in theirs]:
        problems.append(f"{where}: {name}{_signature_text(mine)} is documented, but the real signature is "
                        f"{name}{_signature_text(theirs)}")
    real_params = sig.parameters
    for pname, _, default in mine:
        if default is None or pname not in real_params:
            continue
        if isinstance(default, ast.Constant) and default.value is Ellipsis:
            continue  # elided
        want = real_params[pname].default
        if want is inspect.Parameter.empty:
            problems.append(f"{where}: {name}: parameter {pname} is documented with the default "
                            f"{ast.unparse(default)}, but it has none")
            continue
        try:
            got = _value(default, namespace, f"{name}: the default of {pname}")
        except LookupError as exc:
            problems.append(f"{where}: {exc}")
            continue
        if not (got is want or _equal(got, want)):
            shown = ast.unparse(default) + ("" if isinstance(default, ast.Constant) else f" (= {got!r})")
            problems.append(f"{where}: {name}: parameter {pname} is documented with the default {shown}, "
                            f"but it is {want!r}")
    if returns is not None:
        problems += _compare_return(returns, sig.return_annotation, where, name)
    return problems


def _equal(a: Any, b: Any) -> bool:
    try:
        return bool(a == b)
    except Exception:  # arrays, tensors: not a default anyone writes
        return False


def _compare_return(returns: ast.expr, real: Any, where: str, name: str) -> list[str]:
    """A written return annotation against the real one: the same text, or for a documented tuple of
    words (``-> (cube, info)``) a real ``tuple[…]`` of as many items."""
    if real is inspect.Signature.empty:
        return [f"{where}: {name}: documented as returning {ast.unparse(returns)}, but it has no return annotation"]
    text = _annotation_text(real)
    if isinstance(returns, ast.Tuple):
        node = ast.parse(text, mode="eval").body
        ok = (isinstance(node, ast.Subscript) and ast.unparse(node.value) in ("tuple", "Tuple")
              and isinstance(node.slice, ast.Tuple) and len(node.slice.elts) == len(returns.elts))
    else:
        ok = ast.unparse(returns) == text
    return [] if ok else [f"{where}: {name}: documented as returning {ast.unparse(returns)}, but it returns {text}"]


# --------------------------------------------------------------------------- listings


def listing_entries(block: Block) -> list[tuple[int, str, str]]:
    """(document line, code, comments) of each entry: lines joined until their brackets balance."""
    out, code, notes, start = [], [], [], 0
    for no, line in enumerate(block.code.splitlines(), block.line):
        text, note = _strip_comment(line)
        if not code and not text.strip():
            continue
        start = start if code else no
        code.append(text.strip())
        notes.append(note)
        joined = " ".join(code)
        if sum(1 if c in "([{" else -1 if c in ")]}" else 0 for _, c, _ in _scan(joined)) <= 0:
            out.append((start, joined, " ".join(n for n in notes if n)))
            code, notes = [], []
    if code:
        out.append((start, " ".join(code), " ".join(notes)))
    return out


def check_listing(block: Block, module_name: str) -> list[str]:
    """What a listing of signatures of ``module_name`` gets wrong (see the module docstring)."""
    module = importlib.import_module(module_name)
    namespace = vars(module)
    problems = []
    for line, code, notes in listing_entries(block):
        where = f"{block.file}:{line}"
        call, returns = _split_arrow(code)
        m = re.match(r"([A-Za-z_][\w.]*)\s*\(", call)
        if not m or not call.endswith(")"):
            problems.append(f"{where}: not a signature: {code}")
            continue
        name = m.group(1)
        real: Any = module
        try:
            for part in name.split("."):
                real = getattr(real, part)
        except AttributeError:
            problems.append(f"{where}: {name} is documented, but {module_name} has no {name}")
            continue
        ret = ast.parse(returns, mode="eval").body if returns else None
        try:
            fn = ast.parse(f"def _{call[m.end() - 1:]}: ...").body[0]
        except SyntaxError:  # written as a call: parse_holdout("a,b")
            problems += _check_call(ast.parse(call, mode="eval").body, real, where, name, namespace)
            if ret is not None:
                problems += _compare_return(ret, inspect.signature(real).return_annotation, where, name)
        else:
            problems += compare_signature(fn.args, ret, real, where, name, namespace)
        for word in re.findall(r"\b[A-Z][A-Z0-9]*_[A-Z0-9_]+\b", notes):
            if not hasattr(module, word):
                problems.append(f"{where}: the comment names {word}, which {module_name} does not have")
        for path in re.findall(r"[\w./-]+\.py\b", notes):
            if not (ROOT / path).is_file():
                problems.append(f"{where}: the comment names {path}, which does not exist")
    return problems


def _check_call(call: ast.Call, real: Callable, where: str, name: str, namespace: dict[str, Any]) -> list[str]:
    """A documented call binds to ``real``'s signature (arguments that are not literals or names: any value)."""

    def value(node):
        try:
            return _value(node, namespace, name)
        except LookupError:
            return object()

    try:
        inspect.signature(real).bind(*[value(a) for a in call.args],
                                     **{k.arg: value(k.value) for k in call.keywords if k.arg})
    except TypeError as exc:
        return [f"{where}: {ast.unparse(call)} does not fit {name}{inspect.signature(real)}: {exc}"]
    return []


# --------------------------------------------------------------------------- skeletons


def _cameras() -> dict[str, type]:
    from hsicam.cameras.registry import CAMERAS

    return CAMERAS


def _networks() -> dict[str, Any]:
    from hsicam.models.registry import NETWORKS

    return NETWORKS


def _registered_camera(obj: Any, args: list[Any], kwargs: dict[str, Any]) -> str | None:
    kind = args[0]
    if _cameras().get(kind) is not obj or getattr(obj, "kind", None) != kind:
        return f"camera kind {kind!r} is not {obj.__name__} (registered: {_cameras().get(kind)})"
    return None


def _registered_network(obj: Any, args: list[Any], kwargs: dict[str, Any]) -> str | None:
    kind = args[0]
    entry = _networks().get(kind)
    if entry is None or entry.build is not obj:
        return f"network kind {kind!r} is not built by {obj.__name__} (registered: {entry})"
    for key, want in kwargs.items():
        got = getattr(entry, key)
        if not (got is want or _equal(tuple(got) if isinstance(got, list) else got, want)):
            return f"network kind {kind!r} is registered with {key}={got!r}, not {want!r}"
    return None


#: Decorators a skeleton may use, by name → check(decorated object, args, kwargs) → problem or None.
REGISTRIES: dict[str, Callable[[Any, list[Any], dict[str, Any]], str | None]] = {
    "register_camera": _registered_camera,
    "register_network": _registered_network,
}
_METHOD_DECORATORS = {"classmethod": classmethod, "staticmethod": staticmethod, "property": property}


def _check_decorators(node: ast.ClassDef | ast.FunctionDef, obj: Any, namespace: dict[str, Any],
                      where_of: Callable[[ast.AST], str]) -> list[str]:
    problems = []
    for deco in node.decorator_list:
        call = deco if isinstance(deco, ast.Call) else None
        func = call.func if call else deco
        name = ast.unparse(func)
        where = where_of(deco)
        if name in _METHOD_DECORATORS:
            continue  # checked with the method
        if name not in namespace:
            problems.append(f"{where}: the decorator {name} is not imported or defined")
            continue
        if name not in REGISTRIES:
            problems.append(f"{where}: no check for the decorator {name}: add one to REGISTRIES")
            continue
        try:
            args = [_value(a, namespace, name) for a in (call.args if call else [])]
            kwargs = {k.arg: _value(k.value, namespace, name) for k in (call.keywords if call else [])}
        except LookupError as exc:
            problems.append(f"{where}: {exc}")
            continue
        try:
            inspect.signature(namespace[name]).bind(*args, **kwargs)
        except TypeError as exc:
            problems.append(f"{where}: {ast.unparse(deco)} does not fit "
                            f"{name}{inspect.signature(namespace[name])}: {exc}")
            continue
        why = REGISTRIES[name](obj, args, kwargs)
        if why:
            problems.append(f"{where}: {ast.unparse(deco)}: {why}")
    return problems


def _method(cls: type, node: ast.FunctionDef, where: str, imported: dict[str, Any],
            namespace: dict[str, Any]) -> list[str]:
    """A method of a skeleton class against the real class (looked up along its MRO)."""
    try:
        static = inspect.getattr_static(cls, node.name)
    except AttributeError:
        return [f"{where}: {cls.__name__}.{node.name} is documented, but {cls.__name__} has no {node.name}"]
    decos = [ast.unparse(d) for d in node.decorator_list]
    wrapper = next((_METHOD_DECORATORS[d] for d in decos if d in _METHOD_DECORATORS), None)
    if wrapper is None and isinstance(static, (classmethod, staticmethod, property)):
        return [f"{where}: {cls.__name__}.{node.name} is a {type(static).__name__}, documented as a plain method"]
    if wrapper is not None and not isinstance(static, wrapper):
        return [f"{where}: {cls.__name__}.{node.name} is documented as a {wrapper.__name__}, but it is "
                f"a {type(static).__name__}"]
    fn = static.fget if isinstance(static, property) else getattr(static, "__func__", static)
    if not callable(fn):
        return [f"{where}: {cls.__name__}.{node.name} is not a method"]
    problems = compare_signature(node.args, node.returns, fn, where, f"{cls.__name__}.{node.name}", namespace)
    for base in cls.__mro__[1:]:  # the interface of an imported base that declares it (Camera.A)
        if base in imported.values() and node.name in vars(base):
            base_fn = vars(base)[node.name]
            base_fn = base_fn.fget if isinstance(base_fn, property) else getattr(base_fn, "__func__", base_fn)
            problems += compare_signature(node.args, None, base_fn, where, f"{base.__name__}.{node.name}", namespace)
    return problems


def check_skeleton(block: Block, module_name: str) -> list[str]:
    """What a code outline gets wrong about ``module_name`` (see the module docstring)."""
    module = importlib.import_module(module_name)
    tree = ast.parse(block.padded())

    def where(node: ast.AST) -> str:
        return f"{block.file}:{node.lineno}"

    problems, imported = [], {}
    for node in tree.body:
        if isinstance(node, ast.ImportFrom):
            try:
                source = importlib.import_module(node.module)
            except ImportError as exc:
                problems.append(f"{where(node)}: {ast.unparse(node)}: {exc}")
                continue
            for alias in node.names:
                if not hasattr(source, alias.name):
                    problems.append(f"{where(node)}: {node.module} has no {alias.name}")
                else:
                    imported[alias.asname or alias.name] = getattr(source, alias.name)
        elif isinstance(node, ast.Import):
            for alias in node.names:
                try:
                    imported[alias.asname or alias.name.split(".")[0]] = importlib.import_module(alias.name)
                except ImportError as exc:
                    problems.append(f"{where(node)}: {ast.unparse(node)}: {exc}")
    namespace = {**vars(module), **imported}
    for node in tree.body:
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            continue
        if isinstance(node, ast.Expr) and isinstance(node.value, ast.Constant):
            continue  # ... or a docstring
        if not isinstance(node, (ast.ClassDef, ast.FunctionDef)):
            problems.append(f"{where(node)}: cannot check this statement: {ast.unparse(node)}")
            continue
        obj = getattr(module, node.name, None)
        if obj is None:
            problems.append(f"{where(node)}: {node.name} is documented, but {module_name} has no {node.name}")
            continue
        problems += _check_decorators(node, obj, namespace, where)
        if isinstance(node, ast.FunctionDef):
            problems += compare_signature(node.args, node.returns, obj, where(node), node.name, namespace)
            continue
        if not isinstance(obj, type):
            problems.append(f"{where(node)}: {module_name}.{node.name} is not a class")
            continue
        for base in node.bases:
            real_base = namespace.get(ast.unparse(base))
            if not (isinstance(real_base, type) and issubclass(obj, real_base)):
                problems.append(f"{where(node)}: {node.name} is documented as a subclass of {ast.unparse(base)}, "
                                f"but its bases are {[b.__name__ for b in obj.__mro__[1:]]}")
        for item in node.body:
            if isinstance(item, ast.FunctionDef):
                problems += _method(obj, item, where(item), imported, namespace)
            elif isinstance(item, (ast.Assign, ast.AnnAssign)) and item.value is not None:
                targets = item.targets if isinstance(item, ast.Assign) else [item.target]
                for t in targets:
                    if not hasattr(obj, ast.unparse(t)):
                        problems.append(f"{where(item)}: {node.name}.{ast.unparse(t)} does not exist")
                        continue
                    try:
                        want = ast.literal_eval(item.value)
                    except ValueError:
                        continue
                    got = getattr(obj, ast.unparse(t))
                    if got != want:
                        problems.append(f"{where(item)}: {node.name}.{ast.unparse(t)} is {got!r}, "
                                        f"documented as {want!r}")
            elif not (isinstance(item, ast.Expr) and isinstance(item.value, ast.Constant)):
                problems.append(f"{where(item)}: cannot check this statement: {ast.unparse(item)}")
    for name in sorted(_free_names(tree) - set(namespace)):
        line = next(n.lineno for n in ast.walk(tree) if isinstance(n, ast.Name) and n.id == name)
        problems.append(f"{block.file}:{line}: {name} is used, but neither imported nor in {module_name}")
    return problems


# --------------------------------------------------------------------------- runnable examples


@dataclasses.dataclass(frozen=True)
class Claim:
    """A comment's claim on line ``line``: ``shape`` (the words of ``(a, b, …)``) of the input ``name``,
    or of the assigned targets when ``name`` is None."""

    line: int
    name: str | None
    words: tuple[str, ...]
    targets: ast.expr | None


def _groups(text: str) -> list[tuple[str | None, tuple[str, ...]]]:
    """``label (a, b)`` groups of a comment with at least one comma: (label, words)."""
    return [(m.group(1), tuple(w.strip() for w in m.group(2).split(",")))
            for m in re.finditer(r"(?:(\w+)\s*)?\(([^()]*,[^()]*)\)", text)]


def claims(block: Block) -> list[Claim]:
    """The shape and type claims of the comments of an example's assignments."""
    tree = ast.parse(block.padded())
    notes = _comments(block.padded())
    out = []
    for stmt in tree.body:
        if not isinstance(stmt, ast.Assign):
            continue
        text = " ".join(notes[n] for n in range(stmt.lineno, stmt.end_lineno + 1) if n in notes)
        left, arrow, right = text.partition("->")
        if arrow:
            out += [Claim(stmt.lineno, label, words, None) for label, words in _groups(left)[:1]]
        output = _groups(right if arrow else text)[:1]
        out += [Claim(stmt.lineno, None, words, stmt.targets[0]) for _, words in output]
    return out


def _shape(words: tuple[str, ...], symbols: dict[str, Any], where: str) -> tuple[int, ...] | None:
    """The shape ``(B, 31, H+140, …)`` stands for, None when the words are not sizes."""
    try:
        nodes = [ast.parse(w, mode="eval").body for w in words]
    except SyntaxError:
        return None
    for n in nodes:
        for sub in ast.walk(n):
            if not isinstance(sub, (ast.Name, ast.Constant, ast.BinOp, ast.Add, ast.Sub, ast.Mult, ast.Load)):
                return None
            if isinstance(sub, ast.Name) and sub.id not in symbols:
                return None
    return tuple(int(eval(compile(ast.Expression(n), where, "eval"), {"__builtins__": {}}, dict(symbols)))
                 for n in nodes)


def _check_claim(claim: Claim, ns: dict[str, Any], symbols: dict[str, Any], file: str) -> list[str]:
    where = f"{file}:{claim.line}"
    if claim.name is not None:
        names, values = [claim.name], [ns.get(claim.name)]
    elif isinstance(claim.targets, ast.Tuple) and len(claim.targets.elts) == len(claim.words):
        names = [ast.unparse(t) for t in claim.targets.elts]
        values = [ns.get(n) for n in names]
    else:
        names, values = [ast.unparse(claim.targets)], [ns.get(ast.unparse(claim.targets))]
    shape = _shape(claim.words, symbols, where)
    if shape is not None and len(values) == 1:
        got = tuple(getattr(values[0], "shape", ()))
        return [] if got == shape else [
            f"{where}: {names[0]} is documented as ({', '.join(claim.words)}) = {shape}, but it is {got}"]
    if len(values) == len(claim.words) and all(w.isidentifier() for w in claim.words):
        return [f"{where}: {n} is documented as a {w}, but it is a {type(v).__name__}"
                for n, w, v in zip(names, claim.words, values)
                if not any(k.__name__.lower() == w.lower() for k in type(v).__mro__)]
    return [f"{where}: cannot read the claim ({', '.join(claim.words)}) of {', '.join(names)}: write sizes "
            f"({', '.join(sorted(symbols))}, numbers) or one type per assigned name"]


def run_example(block: Block, spec: Run, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Run ``block`` as written with the names ``spec`` supplies; assert its comments' claims and ``spec.check``."""
    tree = ast.parse(block.padded())
    free = _free_names(tree)
    assert free == set(spec.given), (f"{block}: the example uses names it does not define: {sorted(free)}; the "
                                     f"test supplies {sorted(spec.given)} (a name the prose leaves to the reader "
                                     "goes in Run.given)")
    found = claims(block)
    symbols = {k: v for k, v in spec.symbols.items() if not callable(v)}
    ns: dict[str, Any] = {"__name__": "__doc_example__"}
    gen = torch.Generator().manual_seed(0)
    for name in spec.given:
        shapes = [_shape(c.words, symbols, str(block)) for c in found if c.name == name]
        assert shapes and shapes[0] is not None, \
            f"{block}: no comment documents the shape of {name} (name (B, …) -> …)"
        ns[name] = torch.rand(shapes[0], generator=gen)
    monkeypatch.chdir(tmp_path)
    if spec.prepare:
        spec.prepare(tmp_path)
    exec(compile(block.padded(), str(ROOT / block.file), "exec"), ns)  # noqa: S102 - the documented example
    symbols.update({k: v(ns) for k, v in spec.symbols.items() if callable(v)})
    problems = [p for c in found for p in _check_claim(c, ns, symbols, block.file)]
    assert not problems, "\n".join(problems)
    if spec.check:
        spec.check(ns)


# --------------------------------------------------------------------------- the tests


@pytest.mark.parametrize("block", all_blocks(), ids=str)
def test_documented_python(block, tmp_path, monkeypatch):
    entry = _entry(block)
    if entry is None:
        pytest.fail(f"{block}: a ```python block that is neither run nor checked (first line: {block.first!r}): "
                    "register it in BLOCKS (Run, Listing or Skeleton) or, with a reason, in NOT_CHECKED")
    if isinstance(entry, str):
        pytest.skip(f"not checked: {entry}")
    if isinstance(entry, Run):
        monkeypatch.delenv("HSICAM_PRETRAINED_DIR", raising=False)  # pretrained:NAME is the shipped camera
        run_example(block, entry, tmp_path, monkeypatch)
        return
    problems = (check_excerpt(block, entry.path) if isinstance(entry, Excerpt) else check_listing(block, entry.module)
                if isinstance(entry, Listing) else check_skeleton(block, entry.module))
    assert not problems, "\n".join(problems)


def test_every_registered_block_is_shown():
    """An entry of BLOCKS or NOT_CHECKED whose block is gone (or whose first line changed) is stale."""
    blocks = all_blocks()
    stale = [key for key in [*BLOCKS, *NOT_CHECKED]
             if not any(b.file == key[0] and b.first.startswith(key[1]) for b in blocks)]
    assert not stale, f"no ```python block starts so (registered in BLOCKS / NOT_CHECKED): {stale}"


# -- the checks themselves can fail


def _doc_block(tmp_path: Path, text: str) -> Block:
    path = tmp_path / "doc.md"
    path.write_text(text, encoding="utf-8")
    (block,) = python_blocks(path, tmp_path)
    return block


def test_a_wrong_listing_is_reported_with_its_line(tmp_path):
    block = _doc_block(tmp_path, "Text\n\n```python\nparse_holdout('a')\n"
                                 "spectral_library(bands, holdout=None,\n"
                                 "                 split=\"train\")     # NO_SUCH_NAME\n"
                                 "no_such_function(x)\n"
                                 "dataset_dir(n, size, seed, bands, cache_dir=None) -> int\n```\n")
    problems = "\n".join(check_listing(block, "hsicam.data.synthetic"))
    assert "doc.md:5: spectral_library(bands, holdout, split) is documented, but the real signature is " \
           "spectral_library(bands, holdout_sources, split)" in problems
    assert "doc.md:5: spectral_library: parameter split is documented with the default 'train', but it is 'all'" \
        in problems
    assert "doc.md:5: the comment names NO_SUCH_NAME" in problems
    assert "doc.md:7: no_such_function is documented, but hsicam.data.synthetic has no no_such_function" in problems
    assert "doc.md:8: dataset_dir(n, size, seed, bands, cache_dir) is documented" in problems  # not keyword-only
    assert "doc.md:8: dataset_dir: documented as returning int, but it returns Path" in problems
    assert "doc.md:4" not in problems


def test_a_wrong_skeleton_is_reported_with_its_line(tmp_path):
    block = _doc_block(tmp_path, "```python\nfrom hsicam.cameras.base import Camera, Kamera\n"
                                 "from hsicam.cameras.registry import register_camera\n\n"
                                 "@register_camera(\"sd_cassi\")\n"
                                 "class DDCASSICamera(Camera):\n"
                                 "    has_diagonal_gram = False\n"
                                 "    def from_config(cls, cfg): ...\n"
                                 "    def A(self, y): ...\n"
                                 "    def B(self, y): ...\n```\n")
    problems = "\n".join(check_skeleton(block, "hsicam.cameras.cassi"))
    assert "doc.md:2: hsicam.cameras.base has no Kamera" in problems
    assert "doc.md:5: register_camera('sd_cassi'): camera kind 'sd_cassi' is not DDCASSICamera" in problems
    assert "doc.md:7: DDCASSICamera.has_diagonal_gram is True, documented as False" in problems
    assert "doc.md:8: DDCASSICamera.from_config is a classmethod, documented as a plain method" in problems
    assert ("doc.md:9: DDCASSICamera.A(self, y) is documented, but the real signature is "
            "DDCASSICamera.A(self, x)") in problems
    assert "doc.md:9: Camera.A(self, y) is documented" in problems
    assert "doc.md:10: DDCASSICamera.B is documented, but DDCASSICamera has no B" in problems


def test_a_wrong_excerpt_is_reported_with_its_line(tmp_path):
    block = _doc_block(tmp_path, "```python\nout = args.out or Path(tempfile.mkdtemp(prefix=\"hsicam_psf_\"))\n\n"
                                 "cam = DOECamera.from_config(cfg, 1)\n"
                                 "    cam = DOECamera.from_config(cfg)\n"
                                 "cfg = load_config(\"paper\", [f\"camera.lens.model={args.lens}\", "
                                 "f\"camera.doe.enabled={not args.no_doe}\"])\n```\n")
    problems = check_excerpt(block, "examples/camera_and_psf.py")
    assert problems == ["doc.md:4: 'cam = DOECamera.from_config(cfg, 1)' is not a line of examples/camera_and_psf.py",
                        "doc.md:6: 'cfg = load_config(\"paper\", [f\"camera.lens.model={args.lens}\", "
                        "f\"camera.doe.enabled={not args.no_doe}\"])' comes before "
                        "the line above it in examples/camera_and_psf.py"], problems


def test_an_unregistered_block_fails(tmp_path):
    block = _doc_block(tmp_path, "```python\nimport hsicam\n```\n")
    assert _entry(block) is None


@pytest.mark.parametrize("comment, problem", [
    ("# (B, 1, H, W)", None),
    ("# (B, 2, H, W)", "doc.md:2: y is documented as (B, 2, H, W) = (2, 2, 3, 4), but it is (2, 1, 3, 4)"),
    ("# x (B, 1, H, W) -> (B, 1, H, W)", None),
    ("# x (B, 1, H+1, W) -> (B, 1, H, W)", "doc.md:2: x is documented as (B, 1, H+1, W) = (2, 1, 4, 4)"),
    ("# (a, b), prose", "cannot read the claim (a, b) of y"),
])
def test_comment_claims(tmp_path, comment, problem):
    block = _doc_block(tmp_path, f"```python\ny = x + 0  {comment}\n```\n")
    ns, symbols = {"x": torch.zeros(2, 1, 3, 4), "y": torch.zeros(2, 1, 3, 4)}, {"B": 2, "H": 3, "W": 4}
    got = [p for c in claims(block) for p in _check_claim(c, ns, symbols, block.file)]
    assert (not got) if problem is None else (problem in "\n".join(got)), got
