"""The settings of a run: one frozen dataclass, the single source of the defaults.

``RunSettings`` holds every setting of ``mocap run`` (and of :func:`mocap.run`), grouped in
sections that are the stages' own settings (``reconstruction``, ``labels``, ``rejections``); each
field documents itself in its ``metadata["help"]``. From it come:

- the TOML file ``mocap run --config run.toml`` reads (top-level keys and one table per
  section, the names of the fields; unknown keys and wrong types are errors naming the key);
- the command-line flags of ``mocap run`` (one per setting, ``--min-cameras``,
  ``--fill-gaps-frames``, ... generated from the fields; :func:`add_flags`);
- the listing ``mocap run --print-config`` prints (:func:`describe`);
- ``summary.json``'s ``settings`` (:func:`to_dict`).

Precedence: defaults < the TOML file < flags (or :func:`mocap.run`'s keyword arguments).
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Iterator

from mocap.reconstruction.settings import LabelSettings, ReconstructionSettings, RejectionSettings

RECORD_BLOBS = ("subset", "all", "none")


def _jobs_default() -> int:
    return os.cpu_count() or 1


@dataclass(frozen=True)
class RunSettings:
    """Every setting of a run; defaults follow the paper."""

    reconstruction: ReconstructionSettings = field(
        default=ReconstructionSettings(),
        metadata={"help": "correspondence search and triangulation"})
    labels: LabelSettings = field(
        default=LabelSettings(), metadata={"help": "marker identities and tracking"})
    rejections: RejectionSettings = field(
        default=RejectionSettings(), metadata={"help": "markers and trajectories left out"})
    fill_gaps_frames: int = field(default=0, metadata={
        "help": "interpolate gaps of up to this many frames (flagged in the trajectories)",
        "stage": "reconstruct"})
    analyze: bool = field(default=True, metadata={
        "help": "the paper's analyses, tables and figures (off: an audit-only run)",
        "stage": "analyze"})
    bootstrap_samples: int = field(default=200, metadata={
        "help": "bootstrap replicates (markers resampled) for the properties' confidence "
                "intervals; 0 for none", "stage": "analyze"})
    jobs: int = field(default_factory=_jobs_default, metadata={
        "help": "processes reconstructing takes in parallel (default: all cores; "
                "does not change any result)", "stage": None})
    recording: bool = field(default=True, metadata={
        "help": "write the Rerun recording session.rrd", "stage": "recording"})
    record_blobs: str = field(default="subset", metadata={
        "help": "2D blobs in the recording: 'subset' (wand, rest, first response take), "
                "'all' face takes, or 'none'", "stage": "recording",
        "choices": RECORD_BLOBS})

    def __post_init__(self):
        for f, value in self._leaves():
            _check_type(f"{f}", value, self._leaf_type(f))
        if self.record_blobs not in RECORD_BLOBS:
            raise ValueError(f"record_blobs: expected one of {RECORD_BLOBS}, got {self.record_blobs!r}")
        if self.jobs < 1:
            raise ValueError(f"jobs: expected at least 1, got {self.jobs}")
        if self.reconstruction.min_cameras < 2:
            raise ValueError("reconstruction.min_cameras: expected at least 2, got "
                             f"{self.reconstruction.min_cameras}")
        if self.fill_gaps_frames < 0 or self.bootstrap_samples < 0:
            raise ValueError("fill_gaps_frames and bootstrap_samples: expected >= 0, got "
                             f"{self.fill_gaps_frames} and {self.bootstrap_samples}")

    def _leaves(self) -> Iterator[tuple[str, Any]]:
        for key, value in to_dict(self).items():
            if isinstance(value, dict):
                for k, v in value.items():
                    yield f"{key}.{k}", v
            else:
                yield key, value

    @staticmethod
    def _leaf_type(key: str) -> type:
        return next(s.type for s in settings_table() if s.key == key)


@dataclass(frozen=True)
class Setting:
    """One leaf setting: its dotted ``key`` (``reconstruction.min_cameras``), command-line
    ``flag``, Python ``type``, ``default``, ``help`` and the ``stage`` whose results it changes."""

    key: str
    flag: str
    type: type
    default: Any
    help: str
    stage: str | None
    choices: tuple | None = None


# the stages each section's settings change (the cache keys of mocap.workflows.run.cache follow these)
_SECTION_STAGE = {"reconstruction": "reconstruct", "labels": "reconstruct", "rejections": "trials"}
_TYPES = {"int": int, "float": float, "bool": bool, "str": str}


def _type_of(f: dataclasses.Field) -> type:
    t = f.type if isinstance(f.type, type) else _TYPES.get(str(f.type))
    if t is None:
        raise TypeError(f"setting {f.name}: unsupported type {f.type!r}")
    return t


def settings_table() -> list[Setting]:
    """Every leaf setting of :class:`RunSettings`, in declaration order."""
    rows = []
    for f in dataclasses.fields(RunSettings):
        if dataclasses.is_dataclass(f.default):
            section = f.default
            for g in dataclasses.fields(section):
                rows.append(Setting(f"{f.name}.{g.name}", "--" + g.name.replace("_", "-"),
                                    _type_of(g), getattr(section, g.name),
                                    g.metadata.get("help", ""), _SECTION_STAGE[f.name]))
        else:
            default = f.default if f.default is not dataclasses.MISSING else f.default_factory()
            rows.append(Setting(f.name, "--" + f.name.replace("_", "-"), _type_of(f), default,
                                f.metadata["help"], f.metadata.get("stage"),
                                f.metadata.get("choices")))
    return rows


def _check_type(key: str, value: Any, t: type) -> None:
    ok = isinstance(value, t) and not (t is not bool and isinstance(value, bool))
    if t is float and isinstance(value, int) and not isinstance(value, bool):
        ok = True
    if not ok:
        raise TypeError(f"setting {key}: expected {t.__name__}, got {value!r}")


def to_dict(settings: RunSettings) -> dict:
    """The settings as nested plain values (JSON and TOML ready)."""
    return dataclasses.asdict(settings)


def with_values(settings: RunSettings, values: dict[str, Any], source: str = "settings") -> RunSettings:
    """``settings`` with ``values`` replaced: dotted keys (``reconstruction.min_cameras``), a
    field's bare name when it is unique (``min_cameras``), or a section as a table/dataclass.

    Raises ``KeyError``/``TypeError`` naming the key (and ``source``) for an unknown key or a
    value of the wrong type.
    """
    table = {s.key: s for s in settings_table()}
    short = {}
    for k in table:
        short.setdefault(k.rsplit(".", 1)[-1], []).append(k)
    flat: dict[str, Any] = {}
    for key, value in values.items():
        if key in ("reconstruction", "labels", "rejections"):
            if dataclasses.is_dataclass(value):
                value = dataclasses.asdict(value)
            if not isinstance(value, dict):
                raise TypeError(f"{source}: [{key}] must be a table, got {value!r}")
            for k, v in value.items():
                if f"{key}.{k}" not in table:
                    raise KeyError(f"{source}: unknown setting {key}.{k} "
                                   f"(known: {', '.join(s for s in table if s.startswith(key + '.'))})")
                flat[f"{key}.{k}"] = v
            continue
        full = key if key in table else (short.get(key, [None])[0] if len(short.get(key, [])) == 1 else None)
        if full is None:
            raise KeyError(f"{source}: unknown setting {key!r} (`mocap run --print-config` lists them)")
        flat[full] = value
    nested = to_dict(settings)
    for key, value in flat.items():
        _check_type(key, value, table[key].type)
        if table[key].type is float:
            value = float(value)
        if "." in key:
            sec, k = key.split(".")
            nested[sec][k] = value
        else:
            nested[key] = value
    return RunSettings(reconstruction=ReconstructionSettings(**nested.pop("reconstruction")),
                       labels=LabelSettings(**nested.pop("labels")),
                       rejections=RejectionSettings(**nested.pop("rejections")), **nested)


def from_toml(path: str | os.PathLike, base: RunSettings | None = None) -> RunSettings:
    """Settings from a TOML file (top-level keys and ``[reconstruction]``, ``[labels]``,
    ``[rejections]`` tables), over ``base`` (the defaults when None)."""
    path = Path(path)
    try:
        doc = tomllib.loads(path.read_text(encoding="utf-8"))
    except tomllib.TOMLDecodeError as e:
        raise ValueError(f"{path}: not valid TOML ({e})") from None
    try:
        return with_values(base or RunSettings(), doc, source=str(path))
    except (KeyError, TypeError) as e:
        raise ValueError(str(e).strip("'\"")) from None


def describe() -> str:
    """Every setting with its default and meaning, as a TOML file (valid for ``--config``)."""
    lines = ["# mocap run settings: defaults and meanings. Save as run.toml, edit, then",
             "#   mocap run SESSION --out OUT --config run.toml",
             "# command-line flags override the file; summary.json records the effective values.",
             ""]
    rows = settings_table()
    top = [s for s in rows if "." not in s.key]  # TOML: top-level keys before any table
    section = None
    for s in top + [s for s in rows if "." in s.key]:
        sec, _, name = s.key.rpartition(".")
        if sec != section and sec:
            lines += ["", f"[{sec}]  # {RunSettings.__dataclass_fields__[sec].metadata['help']}"]
            section = sec
        if isinstance(s.default, bool):
            value = str(s.default).lower()
        else:
            value = f'"{s.default}"' if isinstance(s.default, str) else repr(s.default)
        extra = f"; one of {', '.join(s.choices)}" if s.choices else ""
        # a machine-dependent default (jobs: the cores) is shown commented out
        comment = "# " if RunSettings.__dataclass_fields__.get(name) is not None and \
            RunSettings.__dataclass_fields__[name].default_factory is not dataclasses.MISSING else ""
        lines.append(f"{comment}{name} = {value}  # {s.help}{extra} [{s.flag}]")
    return "\n".join(lines) + "\n"


def add_flags(parser: argparse.ArgumentParser) -> None:
    """One flag per setting (``--min-cameras``...), default ``None`` (not given)."""
    group = parser.add_argument_group("settings (see --print-config; they override --config)")
    for s in settings_table():
        dest = "setting:" + s.key
        if s.type is bool:
            group.add_argument(s.flag, dest=dest, action=argparse.BooleanOptionalAction,
                               default=None, help=f"{s.help} (default {s.default})")
        else:
            group.add_argument(s.flag, dest=dest, type=s.type, default=None, choices=s.choices,
                               metavar=s.type.__name__.upper() if not s.choices else None,
                               help=f"{s.help} (default {s.default})")


def flag_values(args: argparse.Namespace) -> dict[str, Any]:
    """The settings given as flags (dotted keys)."""
    return {k.split(":", 1)[1]: v for k, v in vars(args).items()
            if k.startswith("setting:") and v is not None}
