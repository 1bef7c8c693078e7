"""Packaging and layering: every subpackage ships, the core stays light, and what a user
installs says the right version, Pythons, licence, citation and URLs."""

from __future__ import annotations

import subprocess
import sys
from importlib.metadata import distribution, metadata
from pathlib import Path

import pytest
import yaml

if sys.version_info >= (3, 11):
    import tomllib
else:  # Python 3.10: the backport (pytest depends on it there)
    import tomli as tomllib

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.skipif(not (ROOT / "bopsurg").is_dir(), reason="runs on the checkout only")
def test_every_package_folder_is_listed_in_pyproject():
    cfg = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]["setuptools"]
    listed = set(cfg["packages"])
    dirs = cfg["package-dir"]
    found = set()
    for name, folder in dirs.items():
        base = ROOT / folder
        for init in base.rglob("__init__.py"):
            rel = init.parent.relative_to(base)
            if any(part.startswith(".") or part == "__pycache__" for part in rel.parts):
                continue
            sub = ".".join((name, *rel.parts)) if rel.parts else name
            # subfolders of generators/ and models/ are reached through their own mapping
            if name == "bopsurg" and rel.parts and rel.parts[0] in ("generators", "models"):
                continue
            found.add(sub)
    assert found <= listed, f"packages missing from pyproject: {sorted(found - listed)}"


def test_core_import_pulls_no_heavy_or_plugin_module():
    code = (
        "import sys, bopsurg, bopsurg.metrics, bopsurg.bop, bopsurg.evaluation.runner, "
        "bopsurg.cli.main, bopsurg.visibility\n"
        "bad = [m for m in ('torch', 'pybullet', 'rerun', 'rosbags', 'bopsurg.generators', "
        "'bopsurg.models') if m in sys.modules]\n"
        "print(','.join(bad))"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.strip() == ""


# --- what a user installs: versions, licence, citation, URLs, extras, shipped files ----------

SUPPORTED = ("3.10", "3.11", "3.12", "3.13")
REPO_URL = "https://github.com/bopsurg/bopsurg"
DOCS_URL = "https://bopsurg.github.io/bopsurg"
SOURCE_TREE = (ROOT / "bopsurg" / "_version.py").is_file()  # not in the installed-wheel runs
needs_source = pytest.mark.skipif(not SOURCE_TREE, reason="runs on the checkout only")


def _project() -> dict:
    return tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]


def test_installed_metadata_matches_the_version_and_pythons():
    from bopsurg._version import __version__

    meta = metadata("bopsurg")
    assert meta["Version"] == __version__ == "0.2.0"
    assert meta["Requires-Python"] == ">=3.10"
    classifiers = meta.get_all("Classifier") or []
    for v in SUPPORTED:
        assert f"Programming Language :: Python :: {v}" in classifiers
    assert f"{sys.version_info.major}.{sys.version_info.minor}" in SUPPORTED
    urls = dict(u.split(", ", 1) for u in meta.get_all("Project-URL") or [])
    assert urls["Homepage"] == REPO_URL
    assert urls["Documentation"] == DOCS_URL
    assert not any("example.invalid" in u for u in urls.values())
    assert meta["License-Expression"] == "MIT"
    if not SOURCE_TREE:  # the installed wheel (a checkout may hold a build's egg-info instead)
        assert "LICENSE" in {f.name for f in distribution("bopsurg").files or []}


def test_extras_install_only_what_they_need():
    extras = _project()["optional-dependencies"]
    assert [r.split(">=")[0] for r in extras["vsd"]] == ["pybullet"]  # VSD needs no rosbags
    assert {"pybullet", "rosbags"} <= {r.split(">=")[0] for r in extras["sim"]}
    core = " ".join(_project()["dependencies"])
    for heavy in ("torch", "pybullet", "rosbags", "rerun", "ray"):
        assert heavy not in core


def test_the_depth_renderer_of_vsd_imports_no_rosbags():
    pytest.importorskip("pybullet")
    code = (
        "import sys\nfrom bopsurg.plugins import load_plugin\nload_plugin('renderer', 'pybullet')\n"
        "print('rosbags' in sys.modules, 'torch' in sys.modules)"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert out.stdout.split() == ["False", "False"]


def test_shipped_recipes_are_package_data():
    from bopsurg.cli.recipes_cmd import recipe_path, shipped_recipes

    recipes = shipped_recipes()
    assert "finetune_wide_pose" in recipes
    assert "finetune_wide_detector" in recipes
    for name, path in recipes.items():
        assert recipe_path(name) == recipe_path(f"{name}.yaml") == path
        assert isinstance(yaml.safe_load(path.read_text(encoding="utf-8")), dict)


@needs_source
def test_licence_and_citation_agree_with_the_package():
    from bopsurg._version import __version__

    licence = (ROOT / "LICENSE").read_text()
    assert licence.startswith("MIT License")
    assert "bopsurg developers" in licence
    assert _project()["license"] == "MIT"
    cff = yaml.safe_load((ROOT / "CITATION.cff").read_text())
    assert cff["version"] == __version__
    assert cff["license"] == "MIT"
    assert cff["repository-code"] == REPO_URL
    assert cff["url"] == DOCS_URL
    paper = cff["references"][0]
    assert paper["doi"] == "10.48550/arXiv.2406.07328"
    assert [a["family-names"] for a in paper["authors"]] == [
        "Barragan", "Zhang", "Zhou", "Munawar", "Kazanzides",
    ]  # fmt: skip
    assert paper["title"] == (
        "Realistic Data Generation for 6D Pose Estimation of Surgical Instruments"
    )


@needs_source
def test_no_placeholder_url_is_left():
    tracked = subprocess.run(
        ["git", "grep", "-l", "example.invalid", "--", ".", ":!tests/test_packaging.py"],
        cwd=ROOT, capture_output=True, text=True,
    )  # fmt: skip
    assert tracked.stdout == ""
