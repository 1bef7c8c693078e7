"""The documentation's code is true: every fenced block of README.md, docs/*.md, the model card
and the changelog is run or checked.

- ``python`` blocks run in a temporary folder. A block that needs data or a GPU carries the
  marker comment ``# docs-test: skip (<reason>)``; it is compiled, not run.
- ``bash`` blocks: every ``bopsurg ...`` command is parsed by the real argument parser (the
  command must exist, its options must be known, its arguments complete); ``python
  bench/X.py`` needs the script, ``python -m M`` an importable module, ``make T`` a Makefile
  target, ``pip install "bopsurg[E]"`` an extra in pyproject.toml.
- The README's table of extras lists exactly pyproject's extras; mkdocs.yml's nav lists
  every page of docs/ and only those.

Commands, extras and files that other branches of the 0.2.0 release add are listed in
``PENDING_*``: where they are missing from this checkout the check is skipped with that
reason; once they exist they are checked like the rest.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib.util
import io
import re
import shlex
import textwrap
from dataclasses import dataclass
from pathlib import Path

import pytest
import tomllib
import yaml

from bopsurg.cli.commands import CORE
from bopsurg.cli.main import build_parser, main
from bopsurg.plugins import available_plugins

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
SKIP_MARKER = "# docs-test: skip"

#: Added by other branches of the 0.2.0 release (issue #40); checked once they are here.
PENDING_COMMANDS = {"inspect": "bopsurg inspect (real dVRK recordings)", "export": "ONNX export"}
PENDING_EXTRAS = {"vsd", "onnx"}
PENDING_FILES = {"LICENSE", "CITATION.cff"}

SHELL_LANGS = {"bash", "sh", "shell", "console"}
FENCE = re.compile(
    r"^(?P<indent>[ \t]*)(?P<fence>`{3,}|~{3,})(?P<info>[^\n`]*)\n"  # opening fence, language
    r"(?P<body>.*?)^(?P=indent)(?P=fence)[ \t]*$",  # body up to the same fence, same indent
    re.MULTILINE | re.DOTALL,
)


def doc_files() -> list[Path]:
    files = [ROOT / "README.md", ROOT / "CHANGELOG.md", ROOT / "models/weights/MODEL_CARD.md"]
    return [f for f in files if f.exists()] + sorted(DOCS.rglob("*.md"))


@dataclass(frozen=True)
class Block:
    path: Path
    line: int
    lang: str
    code: str

    @property
    def where(self) -> str:
        return f"{self.path.relative_to(ROOT)}:{self.line}"


def fenced_blocks(path: Path) -> list[Block]:
    text = path.read_text(encoding="utf-8")
    blocks = []
    for m in FENCE.finditer(text):
        lang = m["info"].strip().split(" ")[0].lower()
        line = text.count("\n", 0, m.start()) + 1
        blocks.append(Block(path, line, lang, textwrap.dedent(m["body"])))
    return blocks


ALL_BLOCKS = [b for f in doc_files() for b in fenced_blocks(f)]
PYTHON_BLOCKS = [b for b in ALL_BLOCKS if b.lang in ("python", "py")]
SHELL_BLOCKS = [b for b in ALL_BLOCKS if b.lang in SHELL_LANGS]


def shell_commands(block: Block) -> list[tuple[str, list[str]]]:
    """(where, words) of every simple command in a shell block: continuation lines joined,
    comments and a leading ``$ `` prompt dropped, split at ``&&``, ``||``, ``;`` and ``|``,
    leading ``NAME=value`` assignments and ``do``/``then`` dropped. ``$NAME`` expands to the
    block's last ``NAME=value`` or to the first value of ``for NAME in ...``."""
    commands = []
    env: dict[str, str] = {}
    logical = block.code.replace("\\\n", " ")
    for offset, line in enumerate(logical.splitlines()):
        line = line.strip()
        if line.startswith("$ "):
            line = line[2:]
        if not line or line.startswith("#"):
            continue
        lex = shlex.shlex(line, posix=True, punctuation_chars=";&|")
        lex.whitespace_split = True
        lex.commenters = "#"
        words: list[str] = []
        for token in [*lex, ";"]:
            if token not in (";", "&&", "||", "|", "&"):
                words.append(token)
                continue
            while words and words[0] in ("do", "then", "else"):
                words = words[1:]
            if words[:1] == ["for"] and len(words) > 3 and words[2] == "in":
                env[words[1]] = words[3]
            elif words:
                command = _strip_env([_expand(w, env) for w in words], env)
                if command and command != ["done"]:
                    commands.append((f"{block.where}+{offset}", command))
            words = []
    return commands


def _expand(word: str, env: dict[str, str]) -> str:
    return re.sub(r"\$\{?(\w+)\}?", lambda m: env.get(m[1], m[0]), word)


def _strip_env(words: list[str], env: dict[str, str]) -> list[str]:
    """The command after leading ``NAME=value`` assignments, which ``env`` records."""
    while words and (m := re.fullmatch(r"([A-Za-z_]\w*)=(.*)", words[0])):
        env[m[1]] = m[2]
        words = words[1:]
    return words


ALL_COMMANDS = [c for b in SHELL_BLOCKS for c in shell_commands(b)]
BOPSURG_COMMANDS = [(w, c) for w, c in ALL_COMMANDS if c and c[0] == "bopsurg"]


def test_the_docs_have_code_to_check():
    # A regex that stopped matching would make every check below vacuous.
    assert len(PYTHON_BLOCKS) >= 3
    assert len(BOPSURG_COMMANDS) >= 40
    readme = {b.lang for b in ALL_BLOCKS if b.path.name == "README.md"}
    assert {"bash", "python"} <= readme


@pytest.mark.parametrize("block", PYTHON_BLOCKS, ids=lambda b: b.where)
def test_python_block_runs(block, tmp_path, monkeypatch):
    code = compile(block.code, block.where, "exec")
    marker = next(
        (ln for ln in block.code.splitlines() if ln.strip().startswith(SKIP_MARKER)), None
    )
    if marker is not None:
        reason = marker.strip()[len(SKIP_MARKER) :].strip(" ():")
        assert reason, f"{block.where}: say why the block is skipped: {SKIP_MARKER} (reason)"
        pytest.skip(f"compiled only: {reason}")
    monkeypatch.chdir(tmp_path)
    with contextlib.redirect_stdout(io.StringIO()):
        exec(code, {"__name__": "__docs__"})


def _known_commands() -> set[str]:
    return {c.name for c in CORE} | set(available_plugins("command"))


def _subparser(parser: argparse.ArgumentParser, name: str) -> argparse.ArgumentParser:
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            return action.choices[name]
    raise AssertionError("the bopsurg parser has no subcommands")


@pytest.mark.parametrize(("where", "words"), BOPSURG_COMMANDS, ids=[w for w, _ in BOPSURG_COMMANDS])
def test_bopsurg_command_parses(where, words):
    argv = words[1:]
    name = next((a for a in argv if not a.startswith("-")), None)
    if name is not None and name not in _known_commands():
        if name in PENDING_COMMANDS:
            pytest.skip(
                f"'bopsurg {name}' comes with another 0.2.0 branch: {PENDING_COMMANDS[name]}"
            )
        pytest.fail(f"{where}: no command 'bopsurg {name}' (known: {sorted(_known_commands())})")
    parser = build_parser(argv)
    if name is not None and _subparser(parser, name).prefix_chars == "\0":
        pytest.skip(f"'bopsurg {name}' needs an extra that is not installed here")
    err = io.StringIO()
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(err):
        try:
            parser.parse_args(argv)
        except SystemExit as stop:
            if stop.code != 0:
                pytest.fail(f"{where}: `{shlex.join(words)}`\n{err.getvalue()}")


def _makefile_targets() -> set[str]:
    text = (ROOT / "Makefile").read_text()
    return set(re.findall(r"^([A-Za-z][\w-]*)\s*:(?!=)", text, re.MULTILINE))


def _extras() -> set[str]:
    pyproject = tomllib.loads((ROOT / "pyproject.toml").read_text())
    return set(pyproject["project"]["optional-dependencies"])


OTHER_COMMANDS = [
    (w, c)
    for w, c in ALL_COMMANDS
    if c[:1] in (["python"], ["make"]) or c[:2] == ["pip", "install"]
]


@pytest.mark.parametrize(("where", "words"), OTHER_COMMANDS, ids=[w for w, _ in OTHER_COMMANDS])
def test_shell_command_points_at_something_real(where, words):
    if words[0] == "make":
        targets = [w for w in words[1:] if not w.startswith("-") and "=" not in w]
        assert set(targets) <= _makefile_targets(), f"{where}: no Makefile target {targets}"
    elif words[0] == "pip":
        for spec in words[2:]:
            m = re.fullmatch(r"bopsurg\[([\w,-]+)\]", spec)
            if m:
                unknown = set(m[1].split(",")) - _extras() - PENDING_EXTRAS
                assert not unknown, f"{where}: no extra {sorted(unknown)} in pyproject.toml"
    elif words[1:2] == ["-m"]:
        module = words[2]
        assert importlib.util.find_spec(module) is not None, f"{where}: no module {module}"
    elif len(words) > 1 and words[1].endswith(".py"):
        assert (ROOT / words[1]).is_file(), f"{where}: no script {words[1]}"


def test_readme_extras_table_is_pyprojects():
    text = (ROOT / "README.md").read_text()
    table = text.split("| extra |", 1)[1].split("\n\n", 1)[0]
    listed = set(re.findall(r"^\| `([\w-]+)` \|", table, re.MULTILINE))
    assert _extras() <= listed, f"extras missing from the README: {sorted(_extras() - listed)}"
    unknown = listed - _extras() - PENDING_EXTRAS
    assert not unknown, f"the README lists extras pyproject.toml lacks: {sorted(unknown)}"


REPO_FILE = "https://github.com/bopsurg/bopsurg/blob/main/"
SITE = "https://bopsurg.github.io/bopsurg/"


def test_readme_links_to_files_and_pages_that_exist():
    # The README is PyPI's page too, so it links absolutely: to the repository's files and
    # to the docs site's pages, which must exist in this checkout.
    text = (ROOT / "README.md").read_text()
    for target in re.findall(r"\]\(([^)#\s]+)\)", text):
        if target.startswith(REPO_FILE):
            path = target.removeprefix(REPO_FILE)
            assert path in PENDING_FILES or (ROOT / path).exists(), f"no file {path}"
        elif target.startswith(SITE):
            page = target.removeprefix(SITE).strip("/") or "index"
            assert (DOCS / f"{page}.md").exists(), f"the README links to no page: {target}"
        else:
            assert "://" in target, f"README.md: link {target} is relative (broken on PyPI)"


def _nav_pages(node: object) -> list[str]:
    if isinstance(node, str):
        return [node] if node.endswith(".md") else []
    if isinstance(node, dict):
        return [p for v in node.values() for p in _nav_pages(v)]
    if isinstance(node, list):
        return [p for v in node for p in _nav_pages(v)]
    return []


def test_mkdocs_nav_lists_every_page():
    config = yaml.safe_load((ROOT / "mkdocs.yml").read_text())
    nav = set(_nav_pages(config["nav"]))
    pages = {p.relative_to(DOCS).as_posix() for p in DOCS.rglob("*.md")}
    assert nav <= pages, f"nav names missing pages: {sorted(nav - pages)}"
    assert pages <= nav, f"pages not in mkdocs.yml's nav: {sorted(pages - nav)}"


TRAIN_CONFIG_KEYS = {"preset", "seed", "pose", "detector", "recipe", "augment", "loader"}
YAML_BLOCKS = [b for b in ALL_BLOCKS if b.lang in ("yaml", "yml")]


@pytest.mark.parametrize("block", YAML_BLOCKS, ids=lambda b: b.where)
def test_yaml_block_is_a_valid_config(block, tmp_path):
    doc = yaml.safe_load(block.code)
    assert isinstance(doc, dict), f"{block.where}: not a YAML mapping"
    if block.code.lstrip().startswith("# bopsurg predict"):  # a prediction config
        from bopsurg.models.config_tree import from_mapping
        from bopsurg.models.predict_config import PredictConfig

        from_mapping(PredictConfig, doc, block.where)  # raises naming a bad key
        return
    if not set(doc) <= TRAIN_CONFIG_KEYS:
        return  # not a training config: parsing is the check
    if importlib.util.find_spec("torch") is None:
        pytest.skip("checking a training config needs bopsurg[torch]")
    path = tmp_path / "config.yaml"
    path.write_text(block.code)
    kind = "detector" if "detector" in doc else "pose"
    err = io.StringIO()
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(err):
        rc = main(["train", kind, "--config", str(path), "--dump-config"])
    assert rc == 0, f"{block.where}: `bopsurg train {kind} --config` refuses it: {err.getvalue()}"
