"""Every ``hsicam …`` command that README.md, docs/*.md and the shipped cameras' cards show a user
parses with the real parser (:func:`hsicam.cli.build_parser`): the sub-command exists, every option
exists (spelled out: no abbreviation) and takes the arguments shown (and, for reconstruct, passes the
command's own checks of its options together, :data:`OPTION_CHECKS`), and every ``--set key=value``
names a config key (a concrete value is applied through :func:`hsicam.config.load_config`, nothing
is built). A span of options alone (``--flat-mode pixel|cfa``) names options some command has.

What is read: the lines of the shell code blocks (fences without a language, ``bash``, ``sh``,
``console``) that start with a command, and every inline code span holding one (``hsicam …``,
``.venv/bin/hsicam …``, ``python -m hsicam …``, ``torchrun … -m hsicam …``). A code block's line is
a command to copy: its required arguments must be there. An inline span may name a command or an
option (``hsicam evaluate --sensor-sigma``): required arguments may be left out, and an option at
its end may go without its value.

Synopses are expanded: ``[…]`` is optional (each variant has all optional groups, and one has none),
``a|b`` gives one variant per alternative (``[show NAME|copy NAME DIR]`` alternates whole sequences),
``...`` / ``…`` after an argument means "more". Placeholders (``RUN``, ``DIR``, ``SCENE.h5``, ``Y,X``,
``…``) become a value the option takes (its first choice, a number, a path)."""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import functools
import importlib
import io
import re
import types
import typing
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
#: The documents: README, docs/, and the shipped cameras' model cards (`hsicam pretrained show NAME`).
DOCS = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md")),
        *sorted((ROOT / "src" / "hsicam" / "resources" / "pretrained").glob("*/card.md"))]

#: Code spans that hold ``hsicam …`` but are no command to run, (file, span) → why.
NOT_COMMANDS = {
    ("README.md", "hsicam -v COMMAND …"): "the general form of -v (any command), no one command",
    ("docs/usage.md", "hsicam -v COMMAND …"): "the general form of -v (any command), no one command",
    ("docs/data.md", "hsicam write_envi"): "the ENVI description string write_envi writes by default",
    ("docs/hardware.md", "hsicam cube"): "the ENVI description string of an older hsicam's cubes",
    ("docs/hardware.md", "hsicam data crc32 = <hex>"): "an ENVI header key",
}

#: A placeholder word: RUN, DIR_HELDOUT, SCENE.h5, Y,X, FILE.h5.
_PLACEHOLDER = re.compile(r"^[A-Z][A-Z0-9_]*(,[A-Z][A-Z0-9_]*)*(\.[a-z0-9]+)?$")
_ELLIPSIS = ("...", "…")
#: ``--set`` keys shown as placeholders (``--set k=v``, ``--set KEY=VALUE``, ``--set a.b=value``).
_PLACEHOLDER_KEYS = {"k", "key", "KEY", "a.b"}
_SHELL_FENCES = {"", "bash", "sh", "shell", "console"}


@dataclasses.dataclass(frozen=True)
class Shown:
    """A command as a document shows it: where, its text from ``hsicam`` on, and whether it is a
    code block's line (``strict``: runnable as written, required arguments included). ``options``:
    a span of options alone (``--flat-mode pixel|cfa``), of no one command."""

    file: str
    line: int
    text: str
    strict: bool
    options: bool = False

    def __str__(self) -> str:
        return f"{self.file}:{self.line}: {self.text}"


# --------------------------------------------------------------------------- reading the documents


def _strip_comment(line: str) -> str:
    """A shell line without its ``# comment`` (a ``#`` after whitespace, outside quotes)."""
    quote = None
    for i, c in enumerate(line):
        if quote:
            quote = None if c == quote else quote
        elif c in "'\"":
            quote = c
        elif c == "#" and (i == 0 or line[i - 1].isspace()):
            return line[:i].rstrip()
    return line


def _command(text: str) -> str | None:
    """The arguments of the command ``text`` starts with (after ``VAR=value`` words and a launcher,
    ``python -m`` or ``torchrun … -m``), or None when it starts with none."""
    words = text.split()
    while words and re.match(r"^[A-Z_][A-Z0-9_]*=", words[0]):  # OMP_NUM_THREADS=1 hsicam …
        words.pop(0)
    if words[:1] in (["python"], ["python3"], ["torchrun"]) and "-m" in words:
        at = words.index("-m")
        words = words[at + 1:] if words[at + 1:at + 2] == ["hsicam"] else []
    if not words or not re.match(r"^(?:\S*/)?hsicam$", words[0]):
        return None
    return " ".join(words[1:])


def shown_commands(path: Path) -> list[Shown]:
    """Every command ``path`` shows: its shell code blocks' command lines and its inline code spans'
    commands (a span may run over a line break)."""
    name = path.relative_to(ROOT).as_posix()
    lines = path.read_text(encoding="utf-8").splitlines()
    out: list[Shown] = []
    prose: list[tuple[int, str]] = []  # (line number, text) outside fences
    fence = None
    for no, line in enumerate(lines, 1):
        stripped = line.strip()
        if stripped.startswith("```"):
            fence = stripped[3:].strip() if fence is None else None
            prose.append((no, ""))  # a fence ends a paragraph
            continue
        if fence is None:
            prose.append((no, line))
        elif fence in _SHELL_FENCES:
            cmd = _command(_strip_comment(stripped))
            if cmd:
                out.append(Shown(name, no, cmd, strict=True))
    # inline code spans, paragraph by paragraph (a span may run over a line break, never a paragraph's end)
    paragraph: list[tuple[int, str]] = []
    for no, line in [*prose, (0, "")]:
        if line.strip():
            paragraph.append((no, line))
            continue
        text = "\n".join(t for _, t in paragraph)
        for m in re.finditer(r"(?<!`)(`+)(?!`)(.+?)(?<!`)\1(?!`)", text, flags=re.S):
            shown = _from_span(name, paragraph[text.count("\n", 0, m.start())][0], m.group(2))
            out += [shown] if shown is not None else []
        paragraph = []
    return out


def _from_span(name: str, line: int, span: str) -> Shown | None:
    """What an inline code span shows: a command, a command named by its sub-command
    (``evaluate --method dd-cassi-choi --run DIR``), options alone, or nothing."""
    span = " ".join(span.replace("\\|", "|").split())  # a table cell's \| is |
    if (name, span) in NOT_COMMANDS:
        return None
    cmd = _command(span)
    first, _, rest = span.partition(" ")
    if cmd is None and first in _command_paths() and rest.startswith("--"):
        cmd = f"{_command_paths()[first]} {rest}"
    if cmd:
        return Shown(name, line, cmd, strict=False)
    if span.startswith(("--", "[--")):
        return Shown(name, line, span, strict=False, options=True)
    return None


@functools.lru_cache(maxsize=None)
def _command_paths() -> dict[str, str]:
    """Each (sub-)command name that names one command → its words (``pack`` → ``pretrained pack``)."""
    from hsicam.cli import build_parser

    paths: dict[str, list[str]] = {}

    def walk(p, prefix):
        for a in p._actions:
            if isinstance(a, argparse._SubParsersAction):
                for n, sp in a.choices.items():
                    paths.setdefault(n, []).append(" ".join([*prefix, n]))
                    walk(sp, [*prefix, n])

    walk(build_parser(), [])
    return {n: v[0] for n, v in paths.items() if len(v) == 1}


def all_shown() -> list[Shown]:
    return [s for doc in DOCS for s in shown_commands(doc)]


# --------------------------------------------------------------------------- synopses


def _tokens(text: str) -> list[tuple[str, str, bool]]:
    """(kind, text, spaced) of a synopsis: kind 'w' a shell word (quotes removed), '[' and ']' a
    synopsis group, '|' an alternation (spaced: whitespace on a side)."""
    out: list[tuple[str, str, bool]] = []
    word, inside, quote, depth, had_space = "", False, None, 0, True
    i = 0

    def flush():
        nonlocal word, inside
        if inside:
            out.append(("w", word, False))
        word, inside = "", False

    while i < len(text):
        c = text[i]
        if quote:
            if c == quote:
                quote = None
            else:
                word += c
        elif c in "'\"":
            quote, inside = c, True
        elif c.isspace():
            flush()
            depth, had_space = 0, True
            i += 1
            continue
        elif c == "[" and not inside:
            out.append(("[", c, False))
        elif c == "[":
            word, depth = word + c, depth + 1
        elif c == "]" and depth:
            word, depth = word + c, depth - 1
        elif c == "]":
            flush()
            out.append(("]", c, False))
        elif c == "|" and not depth:
            flush()
            nxt = text[i + 1] if i + 1 < len(text) else " "
            out.append(("|", c, had_space or nxt.isspace()))
        else:
            word, inside = word + c, True
        had_space = False
        i += 1
    flush()
    return out


def _parse(tokens: list, i: int = 0, group: bool = False):
    """``(alternatives, next index)``: a sequence (group: up to its ``]``) as its alternatives, each a
    list of items: a word (str), ``("opt", alternatives)`` or ``("alt", alternatives)``."""
    items: list = []
    bars: list[tuple[int, bool]] = []  # (position in items, spaced)
    while i < len(tokens):
        kind, text, spaced = tokens[i]
        if kind == "[":
            alts, i = _parse(tokens, i + 1, group=True)
            items.append(("opt", alts))
            continue
        if kind == "]" and group:
            i += 1
            break
        if kind == "|":
            bars.append((len(items), spaced))
        elif kind == "w":
            items.append(text)
        i += 1
    cuts = [0, *(p for p, _ in bars), len(items)]
    loose = [items[a:b] for a, b in zip(cuts, cuts[1:])]
    if bars and group and (any(s for _, s in bars) or all(
            len(seq) >= 2 and isinstance(seq[0], str) and not seq[0].startswith("-") for seq in loose)):
        return loose, i  # [--config F | --run RUN], [show NAME|copy NAME DIR]
    return [_tight(items, [p for p, _ in bars])], i  # same|valid binds the words beside it


def _tight(items: list, bars: list[int]) -> list:
    """Items with each ``a|b|c`` (bars at those positions) as one ``("alt", …)`` item."""
    out: list = []
    for pos, item in enumerate(items):
        if pos in bars and out:
            prev = out.pop()
            alts = prev[1] if isinstance(prev, tuple) and prev[0] == "alt" else [[prev]]
            word = item
            first = alts[0][0] if isinstance(alts[0][0], str) else ""
            if isinstance(word, str) and "=" in first and "=" not in word:
                word = first.split("=", 1)[0] + "=" + word  # key=null|585: key=585
            elif isinstance(word, str) and word.startswith(".") and "." in first:
                word = first.rsplit(".", 1)[0] + word  # FILE.h5|.hdr: FILE.hdr
            out.append(("alt", [*alts, [word]]))
        else:
            out.append(item)
    return out


def _choices(items: list) -> int:
    n = 1
    for item in items:
        if isinstance(item, tuple):
            n = max(n, len(item[1]) if item[0] == "alt" or len(item[1]) > 1 else 1,
                    *(_choices(seq) for seq in item[1]))
    return n


def _render(items: list, k: int, optional: bool) -> list[str]:
    out: list[str] = []
    for item in items:
        if isinstance(item, str):
            out.append(item)
        elif item[0] == "alt" or optional:
            alts = item[1]
            out += _render(alts[min(k, len(alts) - 1)], k, optional)
    return out


def variants(text: str) -> list[list[str]]:
    """The argument lists a synopsis stands for: one per alternative (every optional group in), and
    one without the optional groups."""
    alts, _ = _parse(_tokens(text))
    out: list[list[str]] = []
    for seq in alts:
        for k in range(_choices(seq)):
            out.append(_render(seq, k, True))
        out.append(_render(seq, 0, False))
    unique: list[list[str]] = []
    for v in out:
        if v not in unique:
            unique.append(v)
    return unique


# --------------------------------------------------------------------------- parsing


def _parsers(p: argparse.ArgumentParser):
    yield p
    for a in p._actions:
        if isinstance(a, argparse._SubParsersAction):
            for sp in a.choices.values():
                yield from _parsers(sp)


def doc_parser(strict: bool) -> argparse.ArgumentParser:
    """The real parser, whose abbreviations are off (a shown ``--sensor-sig`` must not pass for
    ``--sensor-sigma``); not strict: no argument is required."""
    from hsicam.cli import build_parser

    parser = build_parser()
    for p in _parsers(parser):
        assert p.allow_abbrev is False, f"{p.prog}: takes abbreviated options"  # the parser's own, not set here
        if not strict:
            for a in p._actions:
                a.required = False
                if not a.option_strings and a.nargs is None:
                    a.nargs = "?"
    return parser


def _leaf(parser: argparse.ArgumentParser, words: list[str]) -> tuple[argparse.ArgumentParser, int]:
    """The (sub-)parser ``words`` reach and the index of its first argument."""
    i = 0
    while True:
        while i < len(words) and words[i] in ("-v", "--verbose"):
            i += 1
        sub = next((a for a in parser._actions if isinstance(a, argparse._SubParsersAction)), None)
        if sub is None or i >= len(words) or words[i] not in sub.choices:
            return parser, i
        parser, i = sub.choices[words[i]], i + 1


def _is_placeholder(word: str) -> bool:
    return bool(_PLACEHOLDER.match(word)) or "…" in word or word in _ELLIPSIS


def _is_value_placeholder(value: str) -> bool:
    """A ``--set`` value that stands for one: a placeholder, ``…``, or one letter (``=w``, ``=σ``)."""
    return _is_placeholder(value) or "..." in value or bool(re.fullmatch(r"[^\W\d_]", value))


def _dummy(action: argparse.Action) -> str:
    """A value ``action`` takes, for a placeholder."""
    if action.choices:
        return str(next(iter(action.choices)))
    for value in ("dummy", "1", "2", "0.5", "0,0", "cpu", "auto"):  # ("2": a level count, a power of 2; "auto": --orientation)
        try:
            if action.type is not None:
                action.type(value)
            return value
        except (argparse.ArgumentTypeError, ValueError, TypeError):
            continue
    return "dummy"


def concrete(parser: argparse.ArgumentParser, words: list[str], strict: bool) -> list[str]:
    """``words`` with each placeholder a value its option (or positional) takes, a lone ``...``
    dropped, and (not strict) a value added for an option named last without one."""
    leaf, i = _leaf(parser, words)
    out = list(words[:i])
    positionals = [a for a in leaf._actions if not a.option_strings and not isinstance(a, argparse._SubParsersAction)]
    npos = 0
    while i < len(words):
        w = words[i]
        i += 1
        name, eq, value = w.partition("=")
        action = leaf._option_string_actions.get(name) if w.startswith("-") else None
        if action is not None and action.nargs is None and not eq:
            out.append(w)
            if i < len(words):
                value, i = words[i], i + 1
                out.append(_dummy(action) if _is_placeholder(value) and action.dest != "overrides"
                           else value.replace("pretrained:NAME", "pretrained:standard"))
            elif not strict:
                out.append(_dummy(action))
        elif action is not None and eq and _is_placeholder(value) and action.dest != "overrides":
            out.append(f"{name}={_dummy(action)}")
        elif w in _ELLIPSIS:
            continue
        elif _is_placeholder(w) and not w.startswith("-"):
            pos = positionals[npos] if npos < len(positionals) else None
            out.append(_dummy(pos) if pos is not None else "dummy")
            npos += 1
        else:
            if not w.startswith("-"):
                npos += 1
            out.append(w.replace("pretrained:NAME", "pretrained:standard"))
    return out


def parse_error(parser: argparse.ArgumentParser, args: list[str]) -> str | None:
    """argparse's message for ``args``, or None when they parse and pass the command's own checks of
    its options (:data:`OPTION_CHECKS`)."""
    from hsicam.errors import HsicamError

    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        try:
            ns = parser.parse_args(args)
        except SystemExit as exc:
            return err.getvalue().strip() or f"exit {exc.code}"
    module, checks = OPTION_CHECKS.get(getattr(ns, "command", None), (None, ()))
    for check in checks:
        try:
            getattr(importlib.import_module(module), check)(ns)
        except HsicamError as exc:
            return f"hsicam {ns.command}: {exc}"
    return None


#: The checks a command makes of its options alone, before it reads anything: command → (module, functions).
OPTION_CHECKS = {"reconstruct": ("hsicam.cli.reconstruct", ("check_level_options", "check_noise_args"))}


# --------------------------------------------------------------------------- config keys


def _section(tp):
    """The dataclass a config field holds (through Optional), or None for a value."""
    if dataclasses.is_dataclass(tp):
        return tp
    if typing.get_origin(tp) in (typing.Union, types.UnionType):
        return next((a for a in typing.get_args(tp) if dataclasses.is_dataclass(a)), None)
    return None


def config_key_problem(key: str) -> str | None:
    """None when ``key`` (dotted) names a config key (a section or a value), else what is wrong."""
    from hsicam.config import Config

    cls, where = Config, ""
    for part in key.split("."):
        if cls is None:
            return f"config key '{where}' holds a value, not a section"
        hints = typing.get_type_hints(cls)
        if part not in hints:
            return f"unknown config key '{(where + '.' if where else '') + part}'"
        where = f"{where}.{part}" if where else part
        cls = _section(hints[part])
    return None


def set_items(args: list[str]) -> list[str]:
    """The ``--set`` values of an argument list (``--set X`` and ``--set=X``)."""
    out = []
    for i, w in enumerate(args):
        if w == "--set" and i + 1 < len(args):
            out.append(args[i + 1])
        elif w.startswith("--set="):
            out.append(w[len("--set="):])
    return out


def set_problems(args: list[str]) -> list[str]:
    """What is wrong with the ``--set`` items of ``args``: an unknown key, or (placeholders aside)
    a value the config refuses, over the command's preset (``--config NAME``) or, as the command
    line does without one, the built-in defaults."""
    from hsicam.config import load_config, preset_names

    problems, concrete_items = [], []
    for item in set_items(args):
        key, eq, value = item.partition("=")
        key = key.rstrip(".…")
        if not key or key in _PLACEHOLDER_KEYS or key in _ELLIPSIS:
            continue
        why = config_key_problem(key)
        if why is not None:
            problems.append(f"--set {item}: {why}")
        elif eq and value and not _is_value_placeholder(value):
            concrete_items.append(item)
    if concrete_items and not problems:
        base = next((args[i + 1] for i, w in enumerate(args[:-1]) if w == "--config"), None)
        try:
            load_config(base if base in preset_names() else None, concrete_items)
        except Exception as exc:  # noqa: BLE001 - the config's own message is the report
            problems.append(f"--set {' --set '.join(concrete_items)}: {exc}")
    return problems


def problems_of(shown: Shown, parsers: dict[bool, argparse.ArgumentParser]) -> list[str]:
    """Each way in which ``shown`` does not parse, or sets an unknown config key (a span of options
    alone: names an option no command has)."""
    parser = parsers[shown.strict]
    out = []
    for words in variants(shown.text):
        if shown.options:
            known = {o for p in _parsers(parser) for o in p._option_string_actions}
            out += [f"{shown}\n    {w.split('=')[0]}: no hsicam command has this option"
                    for w in words if w.startswith("--") and w.split("=")[0] not in known]
            out += [f"{shown}\n    {p}" for p in set_problems(words)]
            continue
        args = concrete(parser, words, shown.strict)
        why = parse_error(parser, args)
        if why is not None:
            out.append(f"{shown}\n    as `hsicam {' '.join(args)}`: {why}")
        out += [f"{shown}\n    {p}" for p in set_problems(words)]
    return list(dict.fromkeys(out))


@pytest.fixture(scope="module")
def parsers():
    return {True: doc_parser(strict=True), False: doc_parser(strict=False)}


# --------------------------------------------------------------------------- tests


def test_every_documented_command_parses(parsers):
    """Each documented command parses with the real parser and sets only real config keys."""
    shown = all_shown()
    assert len(shown) > 100, len(shown)
    problems = [p for s in shown for p in problems_of(s, parsers)]
    assert not problems, f"{len(problems)} documented command(s) do not work as shown:\n" + "\n".join(problems)


def test_each_document_shows_commands():
    """The reader finds the documents' commands (a change in how they are written must not make them
    invisible to the check)."""
    per_file = {doc.relative_to(ROOT).as_posix(): len(shown_commands(doc)) for doc in DOCS}
    for name in ("README.md", "docs/data.md", "docs/hardware.md", "docs/pretrained.md", "docs/training.md"):
        assert per_file[name] >= 5, per_file
    shown = {s.text for s in shown_commands(ROOT / "README.md")}
    assert "data synth --n 1 --size 256 --seed 3 --split heldout --out scenes" in shown
    assert "reconstruct sim/sensor.npy --run pretrained:standard --out cube.h5" in shown  # comment cut off


def test_not_commands_are_still_shown():
    """Each entry of NOT_COMMANDS is still in its document (a stale entry would hide a real command)."""
    for (name, span) in NOT_COMMANDS:
        assert f"`{span}`" in " ".join((ROOT / name).read_text(encoding="utf-8").split()), (name, span)


@pytest.mark.parametrize("text,expected", [
    ("simulate --scene FILE --out DIR [--boundary same|valid]",
     [["simulate", "--scene", "FILE", "--out", "DIR", "--boundary", "same"],
      ["simulate", "--scene", "FILE", "--out", "DIR", "--boundary", "valid"],
      ["simulate", "--scene", "FILE", "--out", "DIR"]]),
    ("pretrained [show NAME|copy NAME DIR]",
     [["pretrained", "show", "NAME"], ["pretrained", "copy", "NAME", "DIR"], ["pretrained"]]),
    ("psf [--config F | --run RUN] --out DIR",
     [["psf", "--config", "F", "--out", "DIR"], ["psf", "--run", "RUN", "--out", "DIR"], ["psf", "--out", "DIR"]]),
    ("demo --set 'train.freeze=[doe]' [--set x.y=null|585]",
     [["demo", "--set", "train.freeze=[doe]", "--set", "x.y=null"],
      ["demo", "--set", "train.freeze=[doe]", "--set", "x.y=585"],
      ["demo", "--set", "train.freeze=[doe]"]]),
    ("reconstruct S --out FILE.h5|.hdr [--full-well-e E [--read-noise-e R]]",
     [["reconstruct", "S", "--out", "FILE.h5", "--full-well-e", "E", "--read-noise-e", "R"],
      ["reconstruct", "S", "--out", "FILE.hdr", "--full-well-e", "E", "--read-noise-e", "R"],
      ["reconstruct", "S", "--out", "FILE.h5"]]),
])
def test_synopsis_variants(text, expected):
    assert variants(text) == expected


@pytest.mark.parametrize("text,fragment", [
    ("evaluate --run RUN --out DIR --sensor-sigm 0.1", "unrecognized arguments: --sensor-sigm"),  # no abbreviation
    ("evaluate --run RUN --out DIR --no-such-option", "unrecognized arguments: --no-such-option"),
    ("evaluate --run RUN --out DIR --method no-such-method", "invalid choice: 'no-such-method'"),
    ("simulat --scene FILE --out DIR", "invalid choice: 'simulat'"),
    ("train --config quick --resume RUN --out RUN", "unrecognized arguments: dummy"),  # --resume takes no value
    ("train --config quick --set train.no_such_key=3 --out RUN", "unknown config key 'train.no_such_key'"),
    ("train --config quick --set train.epochs=M --set train.no_such_key=M", "unknown config key 'train.no_such_key'"),
    ("train --config quick --set train.epochs=two", "train.epochs"),
    ("reconstruct RAW --run RUN --out c.h5 --exposure-s T", "needs reference_exposure_s (--reference-exposure-s)"),
])
def test_a_wrong_command_is_reported(parsers, text, fragment):
    """The check fails for what a stale document would show (an option renamed in the parser shows as
    the first two)."""
    problems = problems_of(Shown("doc.md", 1, text, strict=False), parsers)
    assert problems and any(fragment in p for p in problems), problems


@pytest.mark.parametrize("text,args", [
    (".venv/bin/hsicam data sources", "data sources"),
    ("python -m hsicam report DIR", "report DIR"),
    ("torchrun --nproc_per_node=4 -m hsicam train --config paper --out RUN", "train --config paper --out RUN"),
    ("OMP_NUM_THREADS=1 hsicam train --config quick --out RUN", "train --config quick --out RUN"),
    ("python scripts/unseen_layouts.py OUT", None),
    ("data: DIR: skipped 2 sub-folder(s) holding hsicam outputs", None),
])
def test_how_a_command_is_told(text, args):
    assert _command(text) == args


def test_an_option_span_with_an_unknown_option_is_reported(parsers):
    problems = problems_of(Shown("doc.md", 1, "--flat-kind pixel|cfa", strict=False, options=True), parsers)
    assert problems and "--flat-kind: no hsicam command has this option" in problems[0], problems
    assert not problems_of(Shown("doc.md", 1, "--flat-mode pixel|cfa", strict=False, options=True), parsers)


def test_a_code_block_command_needs_its_required_arguments(parsers):
    assert problems_of(Shown("doc.md", 1, "train --config quick", strict=True), parsers)
    assert not problems_of(Shown("doc.md", 1, "train --config quick", strict=False), parsers)
