"""The hints in hsicam's messages are true: every string literal and f-string of ``src/hsicam`` (docstrings
aside) is read, as a user who copies from an error, a warning or a ``--help`` would, and each name it gives
is checked against what the code takes:

* ``hsicam COMMAND …`` (in backticks: the whole span; else up to the end of its clause, or the first word
  that is no option, value or placeholder): the command exists, each ``--option`` is one of THAT command's
  (spelled out), a value given to an option with choices is one of them, a ``--set`` item names a config
  key (and a concrete value the config takes). ``data synth --seed``: a command named without ``hsicam``.
* ``--option`` anywhere else: an option of a command that can print the message: a ``hsicam.cli`` module's
  own commands, another module's from :data:`MODULE_COMMANDS`.
* ``key.sub=value`` and dotted ``camera.…`` / ``model.…`` / ``train.…`` / ``data.…`` / ``bands.…`` /
  ``baselines.…`` names: keys of :class:`hsicam.config.Config` (a section or a value); a concrete value
  is one :func:`hsicam.config.load_config` takes (over the defaults, the other items of the same string, or
  a preset).
* ``psf.json`` keys a message asks for (``key: value`` in a message naming psf.json, ``KEY in psf.json``):
  keys :func:`hsicam.data.measured_psf.options_from_manifest` reads, and the values it takes.
* ``docs/NAME.md`` (and a quoted section after it): the file exists, and a heading of it has that title.
* ``HSICAM_*``: an environment variable the code reads (``os.environ`` / ``os.getenv``).
* ``NAME.json`` / ``.yaml`` / ``.safetensors`` / …: a file name the code uses (a string constant equal to
  it, or naming it as ``folder / "NAME"``).

An f-string's fields (``{run}``) and a ``%s`` are placeholders, as ``RUN`` and ``…`` are. Where a string is
no hint, :data:`NOT_HINTS` says why; it must still be in the source (a stale entry fails)."""

from __future__ import annotations

import argparse
import ast
import dataclasses
import difflib
import functools
import re
from pathlib import Path

import pytest

from test_documented_commands import _command_paths, config_key_problem
from test_doc_links import HEADING, _prose_lines

ROOT = Path(__file__).resolve().parents[2]
SRC = ROOT / "src" / "hsicam"

#: What an f-string field or a %-format becomes: a placeholder no check reads as a name.
FIELD = "⟨⟩"

#: Modules whose messages name options → the commands that print them, or whose options they name (a message
#: there names an option of at least one of them). A hsicam.cli module's own commands are added.
MODULE_COMMANDS = {
    "cameras/base.py": {"simulate", "reconstruct", "evaluate", "train", "finetune", "demo", "experiment"},
    "data/images.py": {"reconstruct"},
    "data/measured_psf.py": {"reconstruct", "finetune"},
    "data/datasets.py": {"evaluate", "tolerance", "data show", "train", "finetune", "demo", "experiment"},
    "data/cube.py": {"simulate", "evaluate", "tolerance", "data show", "train", "finetune", "demo", "experiment"},
    "data/pipeline.py": {"train", "finetune", "demo", "experiment", "baseline train-prior", "evaluate"},
    "data/synthetic.py": {"data synth", "train", "finetune", "demo", "experiment", "baseline train-prior",
                          "evaluate", "tolerance"},
    "engine/calibration.py": {"finetune"},
    "cli/baselines.py": {"evaluate"},  # the prior is evaluate --method dd-cassi-choi's --run
    "cli/pretrained.py": {"reconstruct", "evaluate", "finetune"},  # a copied camera is any command's --run
    "engine/cfa_offset.py": {"reconstruct"},
    "engine/demo.py": {"demo"},
    "engine/evaluate.py": {"evaluate", "experiment", "demo"},
    "engine/experiments.py": {"experiment"},
    "engine/loop.py": {"train", "finetune", "demo", "experiment", "baseline train-prior"},
    "engine/methods.py": {"evaluate"},
    # pack reads the results.json of an evaluation: its messages name the options that evaluation took
    "engine/pretrained.py": {"pretrained pack", "evaluate"},
    "engine/prior.py": {"baseline train-prior", "evaluate"},
    "engine/provenance.py": {"train", "finetune", "demo", "experiment", "evaluate", "pretrained pack"},
    "engine/tolerance.py": {"tolerance"},
    "report/tolerance.py": {"tolerance"},
    "runs/camera_files.py": {"simulate", "psf"},
    "engine/train.py": {"train", "demo", "experiment"},
    "export/__init__.py": {"export-optics"},
    "export/tolerance.py": {"export-optics"},
    "models/system.py": {"reconstruct", "evaluate", "pretrained pack"},
    "runs/folder.py": {"train", "finetune", "reconstruct", "evaluate", "tolerance", "export-optics", "psf",
                       "simulate", "pretrained pack", "demo", "experiment", "baseline train-prior"},
    "runs/checkpoint.py": {"train", "finetune", "demo", "experiment", "baseline train-prior"},
    "runs/pretrained.py": {"pretrained show", "pretrained copy", "pretrained pack"},
}

#: Options named for whichever command a user gives them to → why (each must be an option of some command).
GENERIC_OPTIONS = {
    "--run pretrained:": "a shipped camera, for every command that takes a run (`hsicam pretrained` lists them)",
}

#: Strings that hold such a name but are no hint, (file, a fragment of the string) → why.
NOT_HINTS = {
    ("engine/provenance.py", "--name-only"): "an argument of the git command that lists the changed sources",
    ("engine/provenance.py", "--no-renames"): "an argument of the git command that lists the changed sources",
    ("engine/provenance.py", "--no-ext-diff"): "an argument of the git command that lists the changed sources",
    ("engine/provenance.py", "--others"): "an argument of the git command that lists the untracked sources",
    ("engine/provenance.py", "--exclude-standard"): "an argument of the git command that lists the untracked sources",
    ("report/html.py", "--s"): "a CSS custom property (var(--s)) of the report's page",
    ("export/gds.py", "HSICAM_DOE"): "the name of the GDS cell the export writes, no environment variable",
    ("config.py", "model.name (the older spelling of model.kind)"): "names the old key it reads as model.kind",
    ("engine/calibration.py", "camera.optics (DOE)"): "finetune.json's record of the frozen parameter groups",
}

CONFIG_SECTIONS = ("camera", "model", "train", "data", "bands", "baselines")
#: A dotted config key (not part of a longer dotted name: hsicam.data.formats, model.safetensors are no keys).
CONFIG_KEY = re.compile(r"(?<![\w./-])((?:" + "|".join(CONFIG_SECTIONS) + r")(?:\.[a-z_][a-z0-9_]*)+)(\.\*)?"
                        r"(?:=(\[[^\]]*\]|\{[^}]*\}|[^\s,;:()`'\"]+))?")
FILE_SUFFIXES = ("json", "jsonl", "yaml", "safetensors", "csv", "md", "npy", "png", "h5", "hdr", "tif", "tiff", "gds")
#: A file name of hsicam's own (the user's cubes and images, c.h5, psf_450nm.tif, are examples: not checked).
FILE_NAME = re.compile(r"(?<![\w/.{⟩*-])([a-z_][\w-]*\.(?:json|jsonl|yaml|safetensors|csv|md))(?![\w.])")
OPTION = re.compile(r"(?<![\w-])(--[a-z][a-z0-9-]*)")
DOC_REF = re.compile(r"docs/([\w-]+\.md)(?:, ([\"'])(.+?)\2)?")
ENV_VAR = re.compile(r"\bHSICAM_[A-Z0-9_]+\b")


@dataclasses.dataclass(frozen=True)
class Text:
    """A string of the source: its file (relative to src/hsicam), line, and text (fields as :data:`FIELD`)."""

    file: str
    line: int
    text: str

    def __str__(self) -> str:
        return f"src/hsicam/{self.file}:{self.line}: {self.text[:160]!r}"


# --------------------------------------------------------------------------- reading the source


def _docstrings(tree: ast.AST) -> set[int]:
    out = set()
    for n in ast.walk(tree):
        if isinstance(n, (ast.Module, ast.ClassDef, ast.FunctionDef, ast.AsyncFunctionDef)) and n.body:
            first = n.body[0]
            if isinstance(first, ast.Expr) and isinstance(first.value, ast.Constant):
                out.add(id(first.value))
    # a constant's documentation (``#: …`` is a comment; a bare string after an assignment is one too)
    for n in ast.walk(tree):
        for body in (getattr(n, "body", None), getattr(n, "orelse", None)):
            if isinstance(body, list):
                for a, b in zip(body, body[1:]):
                    if isinstance(a, (ast.Assign, ast.AnnAssign)) and isinstance(b, ast.Expr) and \
                            isinstance(b.value, ast.Constant) and isinstance(b.value.value, str):
                        out.add(id(b.value))
    return out


def _text(node: ast.AST) -> str | None:
    if isinstance(node, ast.Constant) and isinstance(node.value, str):
        return node.value
    if isinstance(node, ast.JoinedStr):
        return "".join(v.value if isinstance(v, ast.Constant) else FIELD for v in node.values)
    return None


def texts_of(source: str, name: str) -> list[Text]:
    """The string literals and f-strings of a module's ``source`` (docstrings aside; an f-string whole)."""
    tree = ast.parse(source)
    skip = _docstrings(tree)
    for n in ast.walk(tree):
        if isinstance(n, ast.JoinedStr):
            skip.update(id(v) for v in n.values)
            skip.update(id(s) for v in n.values if isinstance(v, ast.FormattedValue) and v.format_spec is not None
                        for s in ast.walk(v.format_spec))
    out = []
    for n in ast.walk(tree):
        t = _text(n) if id(n) not in skip else None
        if t:
            out.append(Text(name, n.lineno, re.sub(r"%(?:\.\d+)?[sdrgf]", FIELD, t)))
    return out


@functools.lru_cache(maxsize=None)
def source_texts() -> tuple[Text, ...]:
    out: list[Text] = []
    for path in sorted(SRC.rglob("*.py")):
        out += texts_of(path.read_text(encoding="utf-8"), path.relative_to(SRC).as_posix())
    return tuple(out)


def _not_hint(t: Text) -> bool:
    return any(t.file == f and frag in t.text for f, frag in NOT_HINTS)


# --------------------------------------------------------------------------- what the code takes


@functools.lru_cache(maxsize=None)
def parser() -> argparse.ArgumentParser:
    from hsicam.cli import build_parser

    return build_parser()


@functools.lru_cache(maxsize=None)
def command_parsers() -> dict[str, argparse.ArgumentParser]:
    """Each command's words (``data synth``) → its parser."""
    out = {}

    def walk(p, prefix):
        for a in p._actions:
            if isinstance(a, argparse._SubParsersAction):
                for n, sp in a.choices.items():
                    out[" ".join([*prefix, n])] = sp
                    walk(sp, [*prefix, n])

    walk(parser(), [])
    return out


@functools.lru_cache(maxsize=None)
def module_commands() -> dict[str, frozenset[str]]:
    """src-relative module → the commands that can print its messages: a hsicam.cli module's own (those its
    ``register`` adds, sub-commands included), else :data:`MODULE_COMMANDS`."""
    import importlib

    from hsicam.cli import COMMAND_MODULES, _Parser

    out = {k: frozenset(v) for k, v in MODULE_COMMANDS.items()}
    for name in COMMAND_MODULES:  # and the commands a hsicam.cli module registers
        p = _Parser(prog="hsicam")
        sub = p.add_subparsers(dest="command", parser_class=_Parser)
        importlib.import_module(name).register(sub)
        words = set()
        for top, sp in sub.choices.items():
            words.add(top)
            words.update(f"{top} {n}" for a in sp._actions if isinstance(a, argparse._SubParsersAction)
                         for n in a.choices)
        module = name.replace("hsicam.", "").replace(".", "/") + ".py"
        out[module] = out.get(module, frozenset()) | words
    out["cli/__init__.py"] = frozenset(command_parsers())  # shared by every command
    out["cli/args.py"] = frozenset(command_parsers())
    return out


def options_of(command: str) -> dict[str, argparse.Action]:
    return dict(command_parsers()[command]._option_string_actions)


@functools.lru_cache(maxsize=None)
def psf_json_keys() -> frozenset[str]:
    """The psf.json keys hsicam.data.measured_psf reads (``meta.get("KEY")``, ``meta["KEY"]``, ``"KEY" in meta``)."""
    tree = ast.parse((SRC / "data" / "measured_psf.py").read_text(encoding="utf-8"))
    keys = set()
    for n in ast.walk(tree):
        if isinstance(n, ast.Call) and isinstance(n.func, ast.Attribute) and n.func.attr == "get" and \
                isinstance(n.func.value, ast.Name) and n.func.value.id == "meta" and n.args and \
                isinstance(n.args[0], ast.Constant):
            keys.add(n.args[0].value)
        elif isinstance(n, ast.Subscript) and isinstance(n.value, ast.Name) and n.value.id == "meta" and \
                isinstance(n.slice, ast.Constant):
            keys.add(n.slice.value)
        elif isinstance(n, ast.Compare) and isinstance(n.left, ast.Constant) and \
                any(isinstance(c, ast.Name) and c.id == "meta" for c in n.comparators):
            keys.add(n.left.value)
    return frozenset(keys)


def psf_json_value_problem(key: str, value: str) -> str | None:
    """Why psf.json's ``key: value`` is refused by the reader, or None (the reader's own check decides)."""
    import numpy as np
    import yaml

    from hsicam.data.measured_psf import options_from_manifest, subtract_background
    from hsicam.errors import HsicamError

    meta = {"pixel_pitch_um": 5.0, "axis_px": [0, 0], key: yaml.safe_load(value)}
    try:
        opts = options_from_manifest(meta)
        subtract_background(np.ones((16, 16)), opts.background)  # read when the images are
    except HsicamError as exc:
        return str(exc)
    return None


@functools.lru_cache(maxsize=None)
def env_vars_read() -> frozenset[str]:
    """The environment variables the source reads: ``os.environ.get(X)``, ``os.environ[X]``, ``X in os.environ``,
    ``os.getenv(X)``, X a string or a module constant holding one."""
    trees = [ast.parse(p.read_text(encoding="utf-8")) for p in SRC.rglob("*.py")]
    consts = {}
    for tree in trees:
        for n in tree.body:
            if isinstance(n, ast.Assign) and isinstance(n.value, ast.Constant) and isinstance(n.value.value, str):
                consts.update({t.id: n.value.value for t in n.targets if isinstance(t, ast.Name)})

    def value(node):
        if isinstance(node, ast.Constant) and isinstance(node.value, str):
            return node.value
        if isinstance(node, ast.Name):
            return consts.get(node.id)
        return None

    def is_environ(node):
        return isinstance(node, ast.Attribute) and node.attr == "environ" or \
            isinstance(node, ast.Name) and node.id == "environ"

    out = set()
    for tree in trees:
        for n in ast.walk(tree):
            if isinstance(n, ast.Call) and isinstance(n.func, ast.Attribute) and n.args and (
                    n.func.attr in ("get", "pop", "setdefault") and is_environ(n.func.value) or n.func.attr == "getenv"):
                out.add(value(n.args[0]))
            elif isinstance(n, ast.Subscript) and is_environ(n.value):
                out.add(value(n.slice))
            elif isinstance(n, ast.Compare) and any(is_environ(c) for c in n.comparators):
                out.add(value(n.left))
    return frozenset(v for v in out if v)


@functools.lru_cache(maxsize=None)
def file_names_used() -> frozenset[str]:
    """File names the source uses: string constants that are a file name (``"config.yaml"``, ``"NAME.json"``
    with a field before the suffix counts as a pattern), or end in ``/NAME``."""
    names = set()
    for path in SRC.rglob("*.py"):
        tree = ast.parse(path.read_text(encoding="utf-8"))
        for n in ast.walk(tree):
            t = _text(n)
            if t and FILE_NAME.fullmatch(t.rsplit("/", 1)[-1]):
                names.add(t.rsplit("/", 1)[-1])
    return frozenset(names)


# --------------------------------------------------------------------------- the checks


def _placeholder(word: str) -> bool:
    return (FIELD in word or bool(re.fullmatch(r"\{\w*\}", word)) or "…" in word or "..." in word or bool(re.fullmatch(r"[A-Z][A-Z0-9_]*(,[A-Z0-9_]+)*", word))
            or bool(re.fullmatch(r"[A-Z]+[0-9]?", word)))


def config_item_problem(item: str, others: list[str]) -> str | None:
    """Why ``key=value`` (or ``key``) is no config setting: an unknown key, or a concrete value that neither the
    defaults nor (with ``others``, the string's other items) a preset takes; None when fine."""
    from hsicam.config import load_config, preset_names

    key, eq, value = item.partition("=")
    key = key.removesuffix(".*")
    if FIELD in key:
        return None
    why = config_key_problem(key)
    if why is not None:
        return why
    if not eq or not value or _placeholder(value) or re.fullmatch(r"[^\W\d_]", value):
        return None
    errors = []
    for base in (None, *preset_names()):
        for items in ([item], [item, *others]):
            try:
                load_config(base, items)
                return None
            except Exception as exc:  # noqa: BLE001 - the config's message is the report
                errors.append(str(exc))
    return f"{item}: the config refuses it ({errors[0]})"


def _clause(text: str, start: int) -> str:
    """The command that starts at ``start``: up to a closing backtick when it is in backticks, else to the end of
    its clause."""
    before = text[:start]
    if before.count("`") % 2 == 1:
        end = text.find("`", start)
        return text[start:end if end >= 0 else len(text)]
    m = re.compile(r";|\)|\s\(|:\s|,\s|\.\s|\.$|`").search(text, start)
    return text[start:m.start() if m else len(text)]


def command_lines(t: Text) -> list[tuple[int, int, str | None, list[str], bool]]:
    """The commands ``t`` names: (start, end, command words or None for an unknown one, the words after them,
    whether they are in backticks), for ``hsicam COMMAND …`` and a command's words followed by an option."""
    out = []
    paths = command_parsers()
    known_words = set(_command_paths()) | set(paths)
    for m in re.finditer(r"(?<![\w./:-])(hsicam\s+)?([a-z][a-z0-9-]*)(?![\w:-])(?:(?=\s+([a-z][a-z0-9-]*)))?", t.text):
        said_hsicam, w1, w2 = bool(m.group(1)), m.group(2), m.group(3)
        if not said_hsicam and w1 not in known_words:
            continue
        if w2 and f"{w1} {w2}" in paths:
            command = f"{w1} {w2}"
        elif w1 in paths:
            command = w1
        elif w1 in _command_paths():
            command = _command_paths()[w1]
        else:
            command = None
        start = m.start() if said_hsicam else m.start(2)
        clause = _clause(t.text, start)
        words = clause.split()[(1 if said_hsicam else 0) + (len(command.split()) if command and
                                                             command.startswith(w1) else 1):]
        in_backticks = t.text[:start].count("`") % 2 == 1
        if not said_hsicam and not (words[:1] and words[0].startswith("--")):
            # "reconstruct without it: --consistency-steps 0": the command, a few words, a colon, its options
            told = re.match(r"(?:\s+[a-z']+){0,3}:\s+(--[a-z].*?)(?=;|\)|\s\(|,\s|\.\s|\.?$|`)", t.text[m.end(2):])
            if told is None or command is None:
                continue  # a word that names a command in prose ("the train step"), no command line
            clause, words = t.text[start:m.end(2) + told.end()], told.group(1).split()
        out.append((start, start + len(clause), command, words, in_backticks))
    return out


def command_problems(t: Text) -> list[str]:
    """What is wrong with the commands ``t`` names (:func:`command_lines`)."""
    out = []
    for _, _, command, words, in_backticks in command_lines(t):
        if command is None:
            if in_backticks or words[:1] and words[0].startswith("--"):
                out.append(f"{t}\n    hsicam {t.text.split('hsicam', 1)[-1].split()[0]}: no such command")
            continue
        if command in ("data", "baseline", "pretrained") and words[:1] and words[0].startswith("--"):
            out.append(f"{t}\n    hsicam {command} {words[0]}: {command} takes a sub-command first")
            continue
        out += [f"{t}\n    hsicam {command}: {p}" for p in _argument_problems(command, words)]
    return out


def _argument_problems(command: str, words: list[str]) -> list[str]:
    opts = options_of(command)
    positionals = [a for a in command_parsers()[command]._actions if not a.option_strings]
    problems, sets, i, npos = [], [], 0, 0
    while i < len(words):
        w = words[i].strip("'\"").split(FIELD)[0] if words[i].startswith("--") else words[i].strip("'\"")
        i += 1
        if w.startswith("--"):
            name, eq, value = w.partition("=")
            action = opts.get(name)
            if action is None:
                problems.append(f"{name}: not an option of this command")
                continue
            takes = action.nargs != 0 and not isinstance(action, (argparse._StoreTrueAction,
                                                                  argparse._StoreFalseAction))
            if takes and not eq and i < len(words) and not words[i].startswith("--"):
                value, i = words[i].strip("'\""), i + 1
            if takes and value and action.choices and not _placeholder(value) and value not in action.choices:
                problems.append(f"{name} {value}: not one of its choices ({', '.join(map(str, action.choices))})")
            if name == "--set" and value and not _placeholder(value):
                sets.append(value)
        elif _placeholder(w) or "/" in w or "." in w or ":" in w:
            npos += 1
        elif npos < len(positionals) and positionals[npos].choices and w in positionals[npos].choices:
            npos += 1  # hsicam experiment NAME
        else:
            break  # prose after the command
    problems += [p for s in sets if (p := config_item_problem(s, [x for x in sets if x != s]))]
    return problems


def option_problems(t: Text) -> list[str]:
    """Options ``t`` names outside a command line that none of the commands printing it has."""
    commands = module_commands().get(t.file)
    text = t.text
    for start, end, *_ in command_lines(t):  # a command line's options are its command's (command_problems)
        text = text[:start] + " " * (end - start) + text[end:]
    for generic, why in GENERIC_OPTIONS.items():
        text = text.replace(generic, " " * len(generic))
        assert generic.split()[0] in {o for p in command_parsers().values() for o in p._option_string_actions}, why
    found = [m for m in OPTION.finditer(text) if FIELD not in text[m.end():m.end() + 1]]
    if not found:
        return []
    if commands is None:
        return [f"{t}\n    names {found[0].group(1)}: add {t.file} to MODULE_COMMANDS (the commands that print it)"]
    known = set(parser()._option_string_actions).union(*(options_of(c) for c in commands))
    out = [f"{t}\n    {m.group(1)}: an option of none of {', '.join(sorted(commands))}"
           for m in found if m.group(1) not in known]
    # "give --resume the folder …": a value for an option that takes none in every command that prints it
    for m in re.finditer(r"\b(?:give|pass) (--[a-z][a-z0-9-]*) (?:the|a|an|its|this) ", text):
        actions = [options_of(c)[m.group(1)] for c in commands if m.group(1) in options_of(c)]
        if actions and all(a.nargs == 0 for a in actions):
            out.append(f"{t}\n    {m.group(1)} takes no value (a flag) in {', '.join(sorted(commands))}")
    return out


def config_problems(t: Text) -> list[str]:
    items = [(m.group(1) + (m.group(2) or ""), m.group(3)) for m in CONFIG_KEY.finditer(t.text)]
    items = [(k, v) for k, v in items if k.rsplit(".", 1)[-1] not in FILE_SUFFIXES]  # model.safetensors: a file
    concrete = [f"{k}={v}" for k, v in items if v is not None and not _placeholder(v)]
    out = []
    for key, value in items:
        item = key if value is None else f"{key}={value}"
        why = config_item_problem(item, [c for c in concrete if c != item])
        if why:
            out.append(f"{t}\n    {why}")
    return out


def psf_json_problems(t: Text) -> list[str]:
    if "psf.json" not in t.text:
        return []
    out = []
    keys = psf_json_keys()
    # `key: value` (a psf.json setting to write; "value or value2" alternatives)
    for m in re.finditer(r"\b([a-z_]+): ([\w.-]+(?: or [\w.-]+)*)", t.text):
        key, values = m.group(1), m.group(2).split(" or ")
        if key not in keys and "_" not in key and not difflib.get_close_matches(key, keys, cutoff=0.75):
            continue  # prose ("of the peak: 0.2"), not a key misspelt
        if key not in keys:
            out.append(f"{t}\n    {key}: not a psf.json key the reader takes ({', '.join(sorted(keys))})")
            continue
        for v in values:
            why = psf_json_value_problem(key, v) if v not in ("the", "its") else None
            if why:
                out.append(f"{t}\n    psf.json {key}: {v}: {why}")
    # `KEY in psf.json`, `KEY (psf.json)`, `KEY / KEY2 … in psf.json`
    for m in re.finditer(r"((?:[a-z]+_[a-z_]+(?: \[[^\]]*\])?(?: / | and | or |, )?)+)\s*(?:in [^ ]*psf\.json|"
                         r"\(psf\.json\))", t.text):
        for key in re.findall(r"\b[a-z]+_[a-z_]+\b", re.sub(r"\[[^\]]*\]", "", m.group(1))):
            if key not in keys:
                out.append(f"{t}\n    {key}: not a psf.json key the reader takes ({', '.join(sorted(keys))})")
    return out


def headings(path: Path) -> set[str]:
    text = path.read_text(encoding="utf-8")
    return {HEADING.match(raw).group(2).strip() for line, raw in zip(_prose_lines(text), text.splitlines())
            if line and HEADING.match(raw)}


def doc_problems(t: Text) -> list[str]:
    out = []
    for m in DOC_REF.finditer(t.text):
        doc = ROOT / "docs" / m.group(1)
        if not doc.is_file():
            out.append(f"{t}\n    docs/{m.group(1)}: no such document")
        elif m.group(3) and m.group(3) not in headings(doc):
            out.append(f"{t}\n    docs/{m.group(1)}: no heading {m.group(3)!r}")
    return out


def env_problems(t: Text) -> list[str]:
    return [f"{t}\n    {v}: no environment variable hsicam reads" for v in ENV_VAR.findall(t.text)
            if v not in env_vars_read()]


def file_problems(t: Text) -> list[str]:
    return [f"{t}\n    {name}: no file the code reads or writes" for name in FILE_NAME.findall(t.text)
            if name not in file_names_used() and name != t.text]


CHECKS = (command_problems, option_problems, config_problems, psf_json_problems, doc_problems, env_problems,
          file_problems)


def problems_of(t: Text) -> list[str]:
    if _not_hint(t):
        return []
    return list(dict.fromkeys(p for check in CHECKS for p in check(t)))


# --------------------------------------------------------------------------- tests


def test_every_hint_in_the_source_is_true():
    """Each command, option, config key, psf.json key, document, environment variable and file name a message
    of src/hsicam gives is one the code has."""
    texts = source_texts()
    assert len(texts) > 2000, len(texts)
    problems = [p for t in texts for p in problems_of(t)]
    assert not problems, f"{len(problems)} wrong hint(s):\n" + "\n".join(problems)


def test_the_reader_sees_the_hints():
    """The hints are found (a change in how messages are written must not hide them from the checks)."""
    texts = source_texts()
    joined = "\n".join(t.text for t in texts)
    assert joined.count("hsicam train --out") >= 3 and joined.count("--set model.consistency.kind=") >= 2
    assert "psf.json" in joined and "docs/networks.md, 'A TV prior in the steps'" in joined
    assert {"HSICAM_CACHE", "HSICAM_MEMORY_BUDGET_MB", "HSICAM_PRETRAINED_DIR"} <= env_vars_read()
    assert {"pixel_pitch_um", "axis_px", "centre", "background", "normalize", "bands_nm"} <= psf_json_keys()
    assert {"config.yaml", "psf.json", "manifest.json", "metrics.jsonl", "results.json"} <= file_names_used()
    assert "data/images.py" in module_commands() and module_commands()["cli/reconstruct.py"] == {"reconstruct"}


def test_module_commands_name_real_commands_and_modules():
    for module, commands in MODULE_COMMANDS.items():
        assert (SRC / module).is_file(), module
        assert commands <= set(command_parsers()), (module, commands - set(command_parsers()))


def test_not_hints_are_still_in_the_source():
    texts = source_texts()
    for (f, frag), why in NOT_HINTS.items():
        assert any(t.file == f and frag in t.text for t in texts), (f, frag, why)


@pytest.mark.parametrize("file,text,fragment", [
    ("models/system.py", "run `hsicam train --out RUN --resume --set model.consistency.kindd=linear`",
     "unknown config key 'model.consistency.kindd'"),
    ("models/system.py", "run `hsicam train --out RUN --resume --set model.consistency.kind=lineal`", "lineal"),
    ("runs/folder.py", "go on with: hsicam train --out RUN --resumee", "--resumee: not an option of this command"),
    ("runs/folder.py", "hsicam train --run RUN --psf-dir D", "--run: not an option of this command"),
    ("runs/folder.py", "`hsicam evaluate --method no-such --run R --out D`", "--method no-such: not one of"),
    ("runs/folder.py", "`hsicam trian --out R`", "hsicam trian: no such command"),
    ("runs/folder.py", "`hsicam data --out R`", "takes a sub-command first"),
    ("data/measured_psf.py", "the pitch is unknown: pass --psf-pich-um", "--psf-pich-um: an option of none of"),
    ("data/images.py", "pass it: --set model.consistency.kind=landweber", "--set: an option of none of reconstruct"),
    ("runs/folder.py", "or reconstruct without it: --set model.consistency.kind=landweber",
     "hsicam reconstruct: --set: not an option of this command"),
    ("engine/nowhere.py", "pass --out", "add engine/nowhere.py to MODULE_COMMANDS"),
    ("data/datasets.py", "use --set data.npy_band.start_nm=420", "unknown config key 'data.npy_band'"),
    ("engine/loop.py", "raise train.epoch", "unknown config key 'train.epoch'"),
    ("engine/loop.py", "set train.epochs=0", "train.epochs=0: the config refuses it"),
    ("data/measured_psf.py", "set background: borders in psf.json", "psf.json background: borders"),
    ("data/measured_psf.py", "put pixel_pitch in psf.json", "pixel_pitch: not a psf.json key"),
    ("data/measured_psf.py", "set normalise: sum in psf.json", "normalise: not a psf.json key"),
    ("data/measured_psf.py", "use centre: centroid_per_band or axes in psf.json", "psf.json centre: axes"),
    ("engine/loop.py", "see docs/training.md, 'No such section'", "no heading 'No such section'"),
    ("engine/loop.py", "see docs/hardwares.md", "docs/hardwares.md: no such document"),
    ("cli/__init__.py", "lower HSICAM_MEMORY_BUDGET", "HSICAM_MEMORY_BUDGET: no environment variable"),
    ("runs/folder.py", "{run}: no configs.yaml", "configs.yaml: no file the code reads or writes"),
    ("runs/folder.py", "give --restart the folder it was started in", "--restart takes no value (a flag)"),
])
def test_a_wrong_hint_is_reported(file, text, fragment):
    """The checks fail for hints that went stale (an option, key, section or file renamed)."""
    problems = problems_of(Text(file, 1, text))
    assert problems and any(fragment in p for p in problems), problems


@pytest.mark.parametrize("file,text", [
    ("runs/folder.py", f"resume the run to fit it again: hsicam train --out {FIELD} --resume"),
    ("runs/folder.py", f"`hsicam finetune --resume --run {FIELD} --psf-dir DIR --out {FIELD}`"),
    ("models/system.py", "run `hsicam train --out RUN --resume --set model.consistency.kind=linear --set "
                         "model.consistency.iterations=1`"),
    ("engine/pretrained.py", f"(e.g. `hsicam reconstruct SENSOR --run pretrained:{FIELD} --out cube.h5`)"),
    ("cli/camera.py", "every seed key (camera.doe.seed, train.seed, data synth --seed)"),
    ("data/measured_psf.py", "set background: border (or the black level in the files' units) in psf.json"),
    ("cli/reconstruct.py", "speed (docs/networks.md, 'A TV prior in the steps')"),
    ("cli/data.py", "use --set data.npy_bands.start_nm=420"),
    ("engine/tolerance.py", "hsicam reconstruct wrote it; `hsicam psf` refuses such a sensor distance too"),
    ("engine/evaluate.py", "choose another --out, or give --out a folder outside it"),
    ("runs/folder.py", "or without it: reconstruct --consistency-steps 0, evaluate --set model.consistency.kind=landweber"),
])
def test_a_true_hint_passes(file, text):
    assert not problems_of(Text(file, 1, text))
