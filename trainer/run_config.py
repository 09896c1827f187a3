"""The training config a CLI builds: task, variant and preset, a --config file, --set overrides
and the config's own flags (protocad_ros.model.config.Config).

Two generators of options, one per kind: a command's own settings are flat dataclasses beside
the command (trainer.settings.settings_parser: `--field-name`, its help the docstring under the
field, in help groups, with the precedence epilog); the model config is a tree of nested sections
(about 100 fields) whose help is the comment beside or above each field, where the paper's and
the reference implementations' values are cited (protocad_ros.model.hyperparameters). tyro reads
those comments and nests the sections, generating `--section.field` (`--section.no_field` for a
bool) here; settings.py does not reimplement that."""
from __future__ import annotations

import copy
import dataclasses
import typing
from pathlib import Path
from typing import Any, Iterable, Mapping, Sequence

import yaml

from protocad_ros.model.config import apply_overrides, make_config
from protocad_ros.model.hyperparameters import DEFAULT_CLI_PRESET


def parse_set(items: Iterable[str] | None) -> dict[str, Any]:
    """`--set a.b=1 --set c=[1,2]` -> {'a.b': 1, 'c': [1, 2]} (values parsed as YAML)."""
    out: dict[str, Any] = {}
    for item in items or []:
        key, sep, value = item.partition("=")
        if not sep or not key.strip():
            raise ValueError(f"--set expects KEY=VALUE (e.g. train.batch_size=8), got {item!r}")
        out[key.strip()] = yaml.safe_load(value) if value.strip() else ""
    return out


def flatten(d: Mapping[str, Any], prefix: str = "") -> dict[str, Any]:
    out: dict[str, Any] = {}
    for k, v in d.items():
        key = f"{prefix}{k}"
        if isinstance(v, Mapping):
            out.update(flatten(v, key + "."))
        else:
            out[key] = v
    return out


def build_config(task: str | None = None, variant: str | None = None, preset: str | None = None,
                 config_file: str | Path | None = None, overrides: Mapping[str, Any] | None = None):
    """Config from (in increasing priority): preset defaults for task/variant, a YAML file
    (full Config.save() output or a partial nested mapping), `--set` overrides.

    Returns a protocad_ros.model.config.Config.
    """
    file_dict: dict[str, Any] = {}
    if config_file:
        try:
            text = Path(config_file).read_text()
        except OSError as exc:   # missing, a directory, unreadable
            raise ValueError(f"--config {config_file}: {exc.strerror or exc}") from None
        try:
            loaded = yaml.safe_load(text) or {}
        except yaml.YAMLError as exc:
            where = getattr(exc, "problem_mark", None)
            line = f" (line {where.line + 1}, column {where.column + 1})" if where else ""
            raise ValueError(f"--config {config_file}: not valid YAML{line}: "
                             f"{getattr(exc, 'problem', None) or exc}") from None
        if not isinstance(loaded, dict):
            raise ValueError(f"{config_file}: expected a YAML mapping at the top level")
        file_dict = loaded
    # task / variant / preset: flag > file > default
    task = task or file_dict.get("task") or "pendulum_swingup"
    variant = variant or file_dict.get("variant") or "protocad"
    preset = preset or file_dict.get("preset") or DEFAULT_CLI_PRESET
    settings = {k: v for k, v in flatten(file_dict).items() if k not in ("task", "variant", "preset")}
    settings.update(overrides or {})
    # own_settings and reference choose defaults of other fields, so they go to make_config first
    selectors = {k: settings[k] for k in SELECTOR_FIELDS if k in settings}
    cfg = make_config(task=task, preset=preset, variant=variant, **selectors)
    return apply_overrides(cfg, settings)   # ConfigError is a ValueError: one line in the CLIs


#: Config fields that choose the defaults of others (make_config applies their settings first).
SELECTOR_FIELDS = ("own_settings", "reference")

#: Config fields with flags of their own (--task, --variant, --preset: they pick the defaults
#: of every other field), so not among the generated options.
OWN_FLAG_FIELDS = ("task", "variant", "preset")
OWN_SETTINGS_HELP = ("a baseline with the settings it was published with (msgs_docs/training.md, Variants); "
                     "false: ProtoCAD's settings for every variant")


def _config_options_class(cfg: Any) -> type:
    """A dataclass of cfg's sections and settings (not OWN_FLAG_FIELDS), defaults = cfg's values."""
    import tyro

    hints = typing.get_type_hints(type(cfg))
    # A field of the class made here has no comment for tyro to read: the one setting gets its help.
    hints["own_settings"] = typing.Annotated[hints["own_settings"], tyro.conf.arg(help=OWN_SETTINGS_HELP)]  # noqa: F821 - a subscript, not a forward reference
    return dataclasses.make_dataclass("config", [
        (f.name, hints[f.name], dataclasses.field(default_factory=lambda v=getattr(cfg, f.name): copy.deepcopy(v)))
        for f in dataclasses.fields(cfg) if f.name not in OWN_FLAG_FIELDS])


def apply_config_flags(cfg: Any, args: Sequence[str], prog: str) -> Any:
    """cfg with the config options in `args` applied: one option per field of the config tree
    (`--train.batch_size 8`, `--world_model.gru_norm` / `--world_model.no_gru_norm`), generated
    from protocad_ros.model.config by tyro, with the field's comment as help and cfg's value as the
    default shown. `--help` among them prints them and exits; an unknown one exits 2."""
    import tyro

    options = _config_options_class(cfg)
    parsed = tyro.cli(options, args=list(args), prog=prog, use_underscores=True,
                      description="Config options (protocad_ros.model.config; defaults: the chosen "
                                  "--task / --variant / --preset, --config file and --set overrides).")
    cfg = dataclasses.replace(cfg, **{f.name: getattr(parsed, f.name) for f in dataclasses.fields(parsed)})
    cfg.validate()
    return cfg
