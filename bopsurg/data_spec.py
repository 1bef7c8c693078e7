"""The data a recipe trains and selects on, written as data: which splits, made how.

A data spec (a recipe's ``data:`` section, or a file of splits such as
``bench/robust_splits.yaml``) names every split by the ``bopsurg record`` and ``bopsurg
generate`` settings that make it, and which of them train, validate and test::

    splits:
      train_paper_r1: {domain: paper, bags: [501, 502], duration: 30, replays: 24,
                       period: 2, seed: 51}
      val_wide:       {domain: wide, bags: [311, 312], replays: 8, period: 2, seed: 32}
    train: [train_paper_r1]
    val: [val_wide]
    test: []            # sealed splits: measured once per shipped model, never to choose

``bags`` are ``bopsurg record --seed`` values (one episode each, ``duration`` s long), kept as
``BAGS/seed{S}_{duration}s.bag``; ``seed`` is ``bopsurg generate --seed``. A split made by
``bopsurg data`` holds :data:`MARKER`, the spec it was made from: a split without it, or
with another spec, is not ready (:func:`missing_splits`). Every check reports all bad
fields, one line each (:func:`parse_data_spec`).
"""

from __future__ import annotations

import json
from collections.abc import Mapping
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from bopsurg.atomic import write_text
from bopsurg.errors import BopsurgError

#: ``generate --domain`` values a split may name.
DOMAINS = ("paper", "wide")
RGB_FORMATS = ("png", "jpg")
#: The lists of split names a spec may hold, by role.
ROLES = ("train", "val", "test")
#: Written into a split folder once ``generate`` finished it: the spec it was made from.
MARKER = "bopsurg_data.json"
_REQUIRED = ("domain", "bags", "replays", "seed")
_OPTIONAL = {
    "duration": 30.0,
    "period": 2.0,
    "rgb_format": "png",
    "min_visib": 0.1,
    "domain_revision": None,
}


@dataclass(frozen=True)
class SplitSpec:
    """How one split is made.

    Attributes:
        name: The split folder (a training split's name starts with ``train``: generate
            writes the root's test targets for any other).
        domain: ``generate --domain`` (``paper`` or ``wide``).
        bags: ``record --seed`` of each episode, in scene order.
        duration: Episode length, s (``record --duration``).
        replays: Replays per bag (``generate --replays``).
        period: Seconds between frames (``generate --period``).
        seed: ``generate --seed``.
        rgb_format: ``generate --rgb-format`` (png or jpg).
        min_visib: ``generate --min-visib`` (frames whose needle shows less are dropped).
        domain_revision: For ``wide``: the revision of its draw that must have made the
            split (``settings.domain_revision`` of ``bopsurg_generate.json``; a newer bopsurg
            may draw other images from the same seeds), None: any.
    """

    name: str
    domain: str
    bags: tuple[int, ...]
    replays: int
    seed: int
    duration: float = 30.0
    period: float = 2.0
    rgb_format: str = "png"
    min_visib: float = 0.1
    domain_revision: int | None = None

    def bag_path(self, bags_dir: Path, seed: int) -> Path:
        """Where the episode of ``record --seed seed`` is kept."""
        return bags_dir / f"seed{seed}_{self.duration:g}s.bag"

    def record_argv(self, bags_dir: Path, seed: int) -> list[str]:
        """``bopsurg record`` arguments of one of its bags (after the command name)."""
        out = str(self.bag_path(bags_dir, seed))
        return ["--out", out, "--seed", str(seed), "--duration", f"{self.duration:g}"]

    def generate_argv(self, root: Path, bags_dir: Path) -> list[str]:
        """``bopsurg generate`` arguments of the split (after the command name)."""
        return [
            *(str(self.bag_path(bags_dir, s)) for s in self.bags),
            "--out", str(root), "--split", self.name, "--domain", self.domain,
            "--replays", str(self.replays), "--period", f"{self.period:g}",
            "--seed", str(self.seed), "--rgb-format", self.rgb_format,
            "--min-visib", f"{self.min_visib:g}",
        ]  # fmt: skip

    def record(self) -> dict[str, Any]:
        """The spec as plain data (what :data:`MARKER` holds)."""
        out = asdict(self)
        out["bags"] = list(self.bags)
        return out


@dataclass(frozen=True)
class DataSpec:
    """Splits by name, and the names of those that train, validate and test."""

    splits: dict[str, SplitSpec]
    train: tuple[str, ...] = ()
    val: tuple[str, ...] = ()
    test: tuple[str, ...] = ()

    def selected(self, names: tuple[str, ...] | None = None) -> list[SplitSpec]:
        """The splits ``names`` (default: all), in the spec's order.

        Raises:
            BopsurgError: A name the spec does not define.
        """
        if names is None:
            return list(self.splits.values())
        unknown = [n for n in names if n not in self.splits]
        if unknown:
            known = ", ".join(self.splits)
            raise BopsurgError(f"no split {', '.join(unknown)} in the data spec (known: {known})")
        return [self.splits[n] for n in names]


def _integer(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _number(value: Any) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool)


def _field_problem(key: str, value: Any) -> str | None:
    """What is wrong with one field's value, or None."""
    if key == "domain":
        return None if value in DOMAINS else f"must be one of {', '.join(DOMAINS)}, got {value!r}"
    if key == "rgb_format":
        ok = value in RGB_FORMATS
        return None if ok else f"must be one of {', '.join(RGB_FORMATS)}, got {value!r}"
    if key == "bags":
        if not isinstance(value, list) or not value:
            return f"must be a non-empty list of record seeds, got {value!r}"
        if not all(_integer(v) and v >= 0 for v in value):
            return f"record seeds are integers >= 0, got {value!r}"
        return None if len(set(value)) == len(value) else f"a seed is listed twice: {value!r}"
    if key in ("replays", "seed"):
        low = 1 if key == "replays" else 0
        return None if _integer(value) and value >= low else f"must be an integer >= {low}"
    if key == "domain_revision":
        ok = value is None or (_integer(value) and value >= 1)
        return None if ok else f"must be an integer >= 1 (or null), got {value!r}"
    if key == "min_visib":
        ok = _number(value) and 0 <= value <= 1
        return None if ok else f"must be a number in [0, 1], got {value!r}"
    ok = _number(value) and value > 0  # duration, period
    return None if ok else f"must be a number > 0, got {value!r}"


def _split(
    name: str, values: Any, where: str, prefix: str, problems: list[str]
) -> SplitSpec | None:
    """One split's spec, or None with its problems appended (one line per field)."""
    here = f"{where}: {prefix}splits.{name}"
    if not isinstance(values, Mapping):
        problems.append(f"{here}: expected a mapping of fields, got {values!r}")
        return None
    known = (*_REQUIRED, *_OPTIONAL)
    count = len(problems)
    for key in values:
        if key not in known:
            problems.append(f"{here}.{key}: unknown field (known: {', '.join(known)})")
    for key in _REQUIRED:
        if key not in values:
            problems.append(f"{here}.{key}: missing")
    for key, value in values.items():
        problem = _field_problem(key, value) if key in known else None
        if problem:
            problems.append(f"{here}.{key}: {problem}")
    if values.get("domain_revision") is not None and values.get("domain") != "wide":
        problems.append(f"{here}.domain_revision: only the wide domain has revisions")
    if len(problems) > count:
        return None
    fields = {**_OPTIONAL, **values, "bags": tuple(values["bags"])}
    for key in ("duration", "period", "min_visib"):
        fields[key] = float(fields[key])
    return SplitSpec(name=name, **fields)


def _roles(
    data: Mapping[str, Any], splits: Mapping[str, Any], where: str, prefix: str
) -> dict[str, Any]:
    """The role lists, each a tuple of defined names; problems as one line each."""
    out: dict[str, Any] = {}
    problems: list[str] = []
    seen: dict[str, str] = {}
    for role in ROLES:
        names = data.get(role, [])
        if not isinstance(names, list) or not all(isinstance(n, str) for n in names):
            problems.append(
                f"{where}: {prefix}{role}: expected a list of split names, got {names!r}"
            )
            continue
        for n in names:
            if n not in splits:
                problems.append(f"{where}: {prefix}{role}: {n!r} is not a split of {prefix}splits")
            elif n in seen:
                problems.append(f"{where}: {prefix}{role}: {n!r} is also a {seen[n]} split")
            elif (role == "train") != n.startswith("train"):
                rule = "must" if role == "train" else "must not"
                problems.append(
                    f"{where}: {prefix}{role}: {n!r}: a {role} split's name {rule} start "
                    "with 'train' (generate writes the root's test targets for the others)"
                )
            seen[n] = role
        out[role] = tuple(names)
    if problems:
        raise BopsurgError("\n".join(problems))
    return out


def parse_data_spec(data: Any, where: str = "data spec", prefix: str = "") -> DataSpec:
    """A :class:`DataSpec` from its mapping (``splits`` and the role lists).

    Raises:
        BopsurgError: Every problem found, one line each: ``WHERE: PREFIXfield: what``:
            unknown keys, missing or bad values, a role naming an undefined split, a split in
            two roles, and a bag or generate seed shared by splits of different roles (their
            images would not be independent).
    """
    if not isinstance(data, Mapping):
        raise BopsurgError(
            f"{where}: {prefix or 'the file'}: expected a mapping (splits, {', '.join(ROLES)})"
        )
    problems = [
        f"{where}: {prefix}{key}: unknown key (known: splits, {', '.join(ROLES)})"
        for key in data
        if key not in ("splits", *ROLES)
    ]
    raw = data.get("splits")
    if not isinstance(raw, Mapping) or not raw:
        problems.append(f"{where}: {prefix}splits: expected a mapping of split name -> its fields")
        raw = {}
    splits = {str(n): _split(str(n), v, where, prefix, problems) for n, v in raw.items()}
    try:
        roles = _roles(data, splits, where, prefix)
    except BopsurgError as err:
        problems.extend(str(err).splitlines())
        roles = {}
    if problems:
        raise BopsurgError("\n".join(problems))
    spec = DataSpec({n: s for n, s in splits.items() if s is not None}, **roles)
    _check_independent(spec, where, prefix)
    return spec


def _check_independent(spec: DataSpec, where: str, prefix: str) -> None:
    """No record seed and no generate seed shared by splits of two roles."""
    problems: list[str] = []
    owner: dict[tuple[str, int], tuple[str, str]] = {}
    for role in ROLES:
        for name in getattr(spec, role):
            s = spec.splits[name]
            for kind, value in [*(("bag", b) for b in s.bags), ("generate seed", s.seed)]:
                first = owner.setdefault((kind, value), (role, name))
                if first[0] != role:
                    problems.append(
                        f"{where}: {prefix}splits.{name}: {kind} {value} is also used by the "
                        f"{first[0]} split {first[1]!r}"
                    )
    if problems:
        raise BopsurgError("\n".join(problems))


def spec_of_file(data: Mapping[str, Any], path: str | Path) -> DataSpec:
    """The data spec of a file's mapping: its ``data:`` section (a recipe) or the whole file
    (a file of splits)."""
    if "data" in data:
        return parse_data_spec(data["data"], str(path), "data.")
    return parse_data_spec(data, str(path))


def is_made(root: Path, spec: SplitSpec) -> bool:
    """Whether ``root`` holds the split, finished and made from ``spec``."""
    marker = root / spec.name / MARKER
    try:
        return bool(json.loads(marker.read_text(encoding="utf-8")) == spec.record())
    except (OSError, ValueError):
        return False


def mark_made(root: Path, spec: SplitSpec) -> None:
    """Record that ``generate`` finished the split from ``spec`` (atomically)."""
    write_text(root / spec.name / MARKER, json.dumps(spec.record(), indent=2) + "\n")


def made_from_other(root: Path, spec: SplitSpec) -> str | None:
    """The fields in which the split's marker differs from ``spec`` (None: no marker, or the
    same spec)."""
    marker = root / spec.name / MARKER
    if not marker.is_file():
        return None
    try:
        old = json.loads(marker.read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return "an unreadable marker"
    new = spec.record()
    diff = [k for k in new if old.get(k) != new[k]] if isinstance(old, dict) else ["all"]
    return ", ".join(diff) if diff else None


def check_revision(root: Path, spec: SplitSpec) -> None:
    """Refuse a split drawn by another revision of its domain than ``spec`` pins.

    Raises:
        BopsurgError: The split's ``bopsurg_generate.json`` names another (or no) revision.
    """
    if spec.domain_revision is None:
        return
    record = root / spec.name / "bopsurg_generate.json"
    try:
        made = json.loads(record.read_text(encoding="utf-8"))["settings"].get("domain_revision")
    except (OSError, ValueError, KeyError, TypeError, AttributeError):
        raise BopsurgError(f"{record}: unreadable, or no settings") from None
    if made != spec.domain_revision:
        raise BopsurgError(
            f"{root / spec.name}: drawn by --domain {spec.domain} revision {made}, the spec "
            f"pins {spec.domain_revision}: this bopsurg draws other images from these seeds"
        )


def missing_splits(root: Path, specs: list[SplitSpec]) -> list[SplitSpec]:
    """The splits of ``specs`` that ``root`` does not hold finished from their spec."""
    return [s for s in specs if not is_made(root, s)]
