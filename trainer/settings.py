"""Typed settings of the commands: each command's protocol is one dataclass with a docstring
per field, and its command line is generated from those dataclasses (`settings_parser`), so
the flags, their help and the object library code receives are one declaration. Library entry
points take these objects; an argparse namespace never leaves this module.

Order of precedence, lowest first (every --help prints it):

  model config   preset defaults of --task / --variant / --preset
                 < the --config FILE < --set KEY=VALUE < shortcut flags (--batch-size, --seq-len,
                 --seed, --precision, and a command's own, e.g. --updates-per-episode)
                 < config options (--train.batch_size 8, ... listed by --help)
  run settings   the field defaults < on --resume, the run's saved settings (run.json) < flags given

A field is declared with `arg(default, *flags, **argparse_options)`; without flags it gets
`--field-name`, its type comes from the annotation (bool: a store_true flag) unless
`type=` says otherwise, and its help is the docstring under it; `arg(default, flag=False)`:
a setting of library callers only, with no option.
"""
from __future__ import annotations

import argparse
import ast
import dataclasses
import inspect
import sys
import textwrap
import typing
from dataclasses import dataclass, field
from functools import lru_cache
from pathlib import Path
from typing import Any, Sequence, TypeVar

from protocad_ros.model.config import check_train_memory
from protocad_ros.model.hyperparameters import PRESETS, VARIANTS
from protocad_ros.model.precision import PRECISIONS
from sim_bridge.contract.contexts import TASKS
from trainer import cli_values, run_config
from trainer.run_input import check_settings_section, load_json_object

S = TypeVar("S")

#: The --threads help of every command that computes (trainer.torch_setup.setup_torch reads it).
THREADS_HELP = ("torch intra-op threads (default 0 = auto: one per core, shared among torchrun's ranks "
                "on this machine; give 1 to runs that compute side by side)")

PRECEDENCE = """\
order of precedence, lowest first:
  model config: preset defaults (--task/--variant/--preset) < --config FILE < --set KEY=VALUE
                < shortcut flags (--batch-size, --seq-len, --seed, --precision, ...) < config options
  run settings: defaults < the run's saved settings (with --resume) < flags given"""


def arg(default: Any = None, *flags: str, **options: Any) -> Any:
    """A settings field with its command-line form: flags (default `--field-name`) and
    argparse options (type, nargs, choices, metavar, action, const, dest-free)."""
    meta = {"flags": flags, "options": options}
    if isinstance(default, (list, dict)):
        return field(default_factory=lambda d=default: type(d)(d), metadata=meta)
    return field(default=default, metadata=meta)


@lru_cache(maxsize=None)
def field_docs(cls: type) -> dict[str, str]:
    """{field: the docstring written under it} (what tyro and Sphinx read as field docs)."""
    docs: dict[str, str] = {}
    for klass in reversed(cls.__mro__):
        if not dataclasses.is_dataclass(klass):
            continue
        try:
            tree = ast.parse(textwrap.dedent(inspect.getsource(klass)))
        except (OSError, TypeError):
            continue
        body = tree.body[0].body
        for stmt, nxt in zip(body, body[1:]):
            if (isinstance(stmt, ast.AnnAssign) and isinstance(stmt.target, ast.Name)
                    and isinstance(nxt, ast.Expr) and isinstance(nxt.value, ast.Constant)
                    and isinstance(nxt.value.value, str)):
                docs[stmt.target.id] = " ".join(nxt.value.value.split())
    return docs


def _base_type(hint: Any) -> tuple[Any, bool]:
    """(element type, is a list) of an annotation such as `int | None` or `list[str]`."""
    args = [a for a in typing.get_args(hint) if a is not type(None)]
    origin = typing.get_origin(hint)
    if origin in (list, tuple):
        return (args[0] if args else str), True
    if args and origin is not None:   # X | None
        return _base_type(args[0])
    return hint, False


def add_settings(parser: argparse.ArgumentParser, cls: type, title: str | None = None,
                 defaults: dict[str, Any] | None = None) -> None:
    """Add one argument per field of the settings class `cls`, in the help group `title` or
    the field's own (`arg(..., group=...)`)."""
    hints = typing.get_type_hints(cls)
    docs = field_docs(cls)
    groups = parser.__dict__.setdefault("_settings_groups", {})
    for f in dataclasses.fields(cls):
        options = dict(f.metadata.get("options", {}))
        if not options.pop("flag", True):   # a library caller's setting: no option of its own
            continue
        flags = f.metadata.get("flags") or (f"--{f.name.replace('_', '-')}",)
        group = options.pop("group", title)
        where = parser if group is None else groups.get(group) or groups.setdefault(
            group, parser.add_argument_group(group))
        exclusive = options.pop("exclusive", None)   # fields of which at most one may be given
        if exclusive:
            where = groups.get(("x", exclusive)) or groups.setdefault(("x", exclusive),
                                                                       where.add_mutually_exclusive_group())
        default = (defaults or {}).get(f.name, f.default if f.default is not dataclasses.MISSING
                                       else f.default_factory())   # type: ignore[misc]
        options.setdefault("help", docs.get(f.name, ""))
        base, is_list = _base_type(hints[f.name])
        if base is bool and "action" not in options:
            options["action"] = "store_true"
        elif options.get("action", "store") in ("store", "append"):
            if base in (int, float, str) and "type" not in options and "choices" not in options:
                options["type"] = base
            if is_list and "nargs" not in options and options.get("action") != "append":
                options["nargs"] = "+"
        if flags[0].startswith("-"):
            where.add_argument(*flags, dest=f.name, default=default, **options)
        else:   # a positional argument: its name is the field's
            where.add_argument(f.name, default=default, **options)


def table_settings(name: str, params: Sequence[Any], forms: dict[str, dict[str, Any] | None]) -> type:
    """A settings class whose fields are the rows of a node's parameter table (rows with name,
    default, description and choices: sim_bridge.nodekit.param_table.Param), so that the node's own
    command line is generated from the parameters it declares: the flag `--name-with-dashes`,
    the row's type, default, choices and description as its help, unless `forms[name]` says
    otherwise (`flags`, a `default` of the command line's own, and what else `arg` takes);
    `forms[name] = None`: no option (another option gives the value)."""
    fields = []
    for p in params:
        form = forms.get(p.name, {})
        if form is None:
            continue
        form = dict(form)
        flags = form.pop("flags", ())
        array = isinstance(p.default, tuple)
        default = form.pop("default", list(p.default) if array else p.default)
        hint: Any = list[str] if array else type(p.default)
        if p.choices:
            form.setdefault("choices", p.choices)
        form.setdefault("help", p.description)
        fields.append((p.name, hint | None if default is None else hint, arg(default, *flags, **form)))
    return dataclasses.make_dataclass(name, fields)


def settings_parser(prog: str, description: str, sections: Sequence[tuple[str | None, type]],
                    defaults: dict[str, Any] | None = None, epilog: str | None = None) -> argparse.ArgumentParser:
    """A command's parser, generated from its settings classes: `sections` ((help group title
    or None, class)) in order; the epilog is the order of precedence where ModelChoice is one."""
    with_config = any(cls is ModelChoice for _, cls in sections)
    parser = argparse.ArgumentParser(prog=prog, description=description,
                                     epilog=PRECEDENCE if with_config else epilog,
                                     formatter_class=cli_values.HelpFormatter)
    for title, cls in sections:
        add_settings(parser, cls, title, defaults)
    parser.settings_classes = tuple(cls for _, cls in sections)   # what tests/docs/test_commands.py checks
    return parser


def build(cls: type[S], values: dict[str, Any]) -> S:
    """An instance of `cls` from the fields present in `values` (the rest keep defaults)."""
    names = {f.name for f in dataclasses.fields(cls)}   # type: ignore[arg-type]
    return cls(**{k: v for k, v in values.items() if k in names})


@dataclass
class Parsed:
    """A command line, parsed: `values` (every field of every section), `given` (only the
    flags written on this command line), `config_args` (config options, for ModelChoice),
    `argv` (as given)."""

    values: dict[str, Any]
    given: dict[str, Any]
    config_args: list[str]
    argv: list[str]
    prog: str

    def get(self, cls: type[S]) -> S:
        return build(cls, self.values)


def parse(parser: argparse.ArgumentParser, argv: Sequence[str] | None,
          config_help: bool = True) -> Parsed:
    """Parse the command's own settings; what is left must be config options (ModelChoice
    reads them). `-h` prints the command's options, then the config options with the defaults
    of the --task / --variant / --preset / --config given."""
    argv = list(sys.argv[1:] if argv is None else argv)
    helps = [x for x in argv if x in ("-h", "--help")]
    ns, rest = parser.parse_known_args([x for x in argv if x not in helps])
    if helps:
        parser.print_help()
        if config_help:
            print(flush=True)
            choice = build(ModelChoice, vars(ns))
            run_config.apply_config_flags(run_config.build_config(choice.task, choice.variant, choice.preset, choice.config),
                                    ["--help"], parser.prog)
        raise SystemExit(0)
    return Parsed(vars(ns), given_flags(parser, argv), rest, argv, parser.prog)


def given_flags(parser: argparse.ArgumentParser, argv: Sequence[str]) -> dict[str, Any]:
    """The settings written on this command line (defaults left out)."""
    copy = argparse.ArgumentParser(prog=parser.prog, add_help=False)   # the same, no defaults
    for action in parser._actions:
        if isinstance(action, argparse._HelpAction):
            continue
        kwargs = {"dest": action.dest, "default": argparse.SUPPRESS}
        if action.option_strings:
            if isinstance(action, argparse._StoreTrueAction):
                copy.add_argument(*action.option_strings, action="store_true", **kwargs)
                continue
            if isinstance(action, argparse._AppendAction):
                kwargs["action"] = "append"
            copy.add_argument(*action.option_strings, nargs=action.nargs, const=action.const,
                              type=action.type, **kwargs)
        else:
            copy.add_argument(action.dest, nargs="*" if action.nargs in ("*", "?") else action.nargs,
                              type=action.type, default=argparse.SUPPRESS)
    ns, _ = copy.parse_known_args(list(argv))
    out = vars(ns)
    for k, v in list(out.items()):   # a positional that got nothing is not given
        if v == [] and not any(a.dest == k and a.option_strings for a in parser._actions):
            out.pop(k)
    return out


def resumed(cls: type[S], saved: dict[str, Any] | None, parsed: Parsed,
            parser: argparse.ArgumentParser, saved_args: list[str] | None = None) -> S:
    """For --resume: the run's saved settings (run.json `settings`; runs written before that
    was saved: their original command line `args`), replaced by the flags given now."""
    if saved is None and saved_args:
        try:
            saved = vars(parser.parse_known_args(saved_args)[0])
        except SystemExit:
            saved = None
    base = build(cls, {**parsed.values, **(saved or {})})
    return dataclasses.replace(base, **{k: v for k, v in parsed.given.items()
                                        if k in {f.name for f in dataclasses.fields(cls)}})


def resumed_from_run(run_dir: str, parsed: Parsed, parser: argparse.ArgumentParser,
                     sections: dict[str, type]) -> dict[str, Any]:
    """`resumed` for each section ({run.json settings key: class}) of the run in run_dir: its
    saved settings, else its saved command line, replaced by the flags given. A run.json whose
    `settings` is not a mapping of mappings (edited by hand) is a ValueError naming it."""
    path = Path(run_dir) / "run.json"
    saved = load_json_object(path) if path.exists() else {}   # one ValueError line if it is not sound
    kept = saved.get("settings") or {}
    if not isinstance(kept, dict) or not all(isinstance(v, dict) for v in kept.values()):
        raise ValueError(f"{run_dir}/run.json: 'settings' is not a mapping of settings sections")
    for key, cls in sections.items():
        check_settings_section(path, key, cls, kept.get(key) or {})
    old_args = saved.get("args")
    if old_args is not None and not (isinstance(old_args, list) and all(isinstance(a, str) for a in old_args)):
        raise ValueError(f"{path}: 'args' is not a list of strings")
    return {key: resumed(cls, kept.get(key), parsed, parser, old_args) for key, cls in sections.items()}


def as_data(settings: Any) -> dict[str, Any]:
    """A settings object as JSON-able data (run.json)."""
    return dataclasses.asdict(settings)


# ---------------------------------------------------------------------- the model config
@dataclass
class ModelChoice:
    """Which agent and config: the options every training command shares."""

    task: str | None = arg(None, choices=sorted(TASKS))
    """task (default: from --config, else pendulum_swingup)"""
    variant: str | None = arg(None, choices=VARIANTS)
    """agent variant (default: from --config, else protocad)"""
    preset: str | None = arg(None, choices=PRESETS)
    """model size preset (default: from --config, else the small preset)"""
    config: str | None = arg(None, metavar="FILE")
    """YAML config (a saved config.yaml or a partial nested mapping)"""
    set: list[str] = arg([], action="append", metavar="KEY=VALUE")
    """config override, e.g. --set world_model.deter=64 --set train.batch_size=8 (repeatable);
    every field is also an option of its own, listed under 'Config options' below"""
    batch_size: int | None = None
    """B (train.batch_size)"""
    seq_len: int | None = None
    """M (train.seq_len)"""
    seed: int = 0
    """seeds model init, sampling and augmentation"""
    device: str = "cpu"
    """cpu, cuda, cuda:N or auto (cuda when available)"""
    threads: int = arg(0, help=THREADS_HELP)
    """torch threads"""
    precision: str | None = arg(None, choices=PRECISIONS)
    """train.precision; auto = bfloat16 where the device has bf16 arithmetic (AVX512-BF16/AMX
    CPUs, Ampere+ GPUs), else float32; bfloat16 given here is kept even where the device emulates
    it (with a warning); unset: the config's train.precision, a request each process resolves
    on its device (bfloat16 becomes float32 where it would be emulated)"""

    def to_config(self, config_args: Sequence[str] = (), prog: str = "protocad",
                  overrides: dict[str, Any] | None = None):
        """The Config, in the order of precedence above; checked against the machine's memory
        before anything is built (ConfigError, a ValueError: one line in the CLIs)."""
        settings = run_config.parse_set(self.set)
        settings.update(overrides or {})
        if self.batch_size is not None:
            settings["train.batch_size"] = self.batch_size
        if self.seq_len is not None:
            settings["train.seq_len"] = self.seq_len
        settings["train.seed"] = self.seed
        if self.precision:   # the request; resolved where the agent is built (agent.use_precision)
            settings["train.precision"] = self.precision
        cfg = run_config.build_config(self.task, self.variant, self.preset, self.config, settings)
        if config_args:
            flagged = run_config.apply_config_flags(cfg, config_args, prog)
            chosen = {k: getattr(flagged, k) for k in run_config.SELECTOR_FIELDS}
            if chosen != {k: getattr(cfg, k) for k in run_config.SELECTOR_FIELDS}:
                # --reference / --no_own_settings pick other defaults: rebuild on them, flags on top
                cfg = run_config.build_config(self.task, self.variant, self.preset, self.config, {**settings, **chosen})
                flagged = run_config.apply_config_flags(cfg, config_args, prog)
            cfg = flagged
        check_train_memory(cfg)
        return cfg
