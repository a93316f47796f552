"""Stage settings -> command line and pipeline parameters, and back.

From a stage's settings dataclass (:mod:`dronecap.settings`) this module generates the
command's argparse options (:func:`add_options`), builds the settings from parsed options
(:func:`from_namespace`) or from ``pipelines.yaml`` parameters (:func:`param_value`,
:func:`from_params`), range-checks them (:func:`check`) and writes them back as a command line
(:func:`command_line`): type conversion, choices and bounds live here, in one place, and every
problem is one line naming the option.

A pipeline parameter has the name of the option without its dashes (``--local-steps`` ->
``local_steps``); a positional option's parameter is its field name.
"""

from __future__ import annotations

import argparse
import dataclasses
import typing
from collections.abc import Iterator
from dataclasses import MISSING, dataclass
from typing import Any

from dronecap.settings import KEY, Meta


@dataclass(frozen=True)
class Option:
    """One command-line option or argument of a settings class, flattened ones included."""

    name: str  # the pipeline parameter name: the long flag without dashes, or the field
    dest: str  # field name, or "field.sub" for a flattened field
    kind: type  # bool, int, float or str (of each item, for a list)
    many: bool  # a list
    default: Any
    required: bool
    meta: Meta

    @property
    def flag(self) -> str:
        """``--name`` (with dashes)."""
        return "--" + self.name.replace("_", "-")

    @property
    def switch(self) -> bool:
        """An on/off flag (``--no-eval``) rather than an option taking a value."""
        flat = self.meta.flat
        return self.kind is bool and not self.many and (flat is None or flat.parse is None)

    @property
    def late(self) -> bool:
        """Parsed when the settings are built (its parse errors are one-line InputErrors), not
        by argparse: a flattened field with its own parser, or a ``late`` setting."""
        return self.meta.late or (self.meta.flat is not None and self.meta.flat.parse is not None)

    def label(self) -> str:
        """How messages name it: the flag, or the argument's name."""
        return self.name if self.meta.positional else self.flag

    def convert(self, text: str) -> Any:
        """One value from text (ValueError when it is not one)."""
        flat = self.meta.flat
        if flat is not None and flat.parse is not None:
            return flat.parse(self.dest.split(".", 1)[1], text)
        return (self.meta.parse or self.kind)(text)


def _kind(hint: Any) -> tuple[type, bool]:
    """(item type, is a list) of a field's type hint; ``X | None`` is X."""
    args = [a for a in typing.get_args(hint) if a is not type(None)]
    if typing.get_origin(hint) is list:
        return args[0], True
    if args and typing.get_origin(hint) is not list:
        return _kind(args[0])
    return hint, False


def options(cls: type) -> list[Option]:
    """The options of settings class ``cls``, in field order."""
    hints = typing.get_type_hints(cls)
    out: list[Option] = []
    for f in dataclasses.fields(cls):
        meta: Meta | None = f.metadata.get(KEY)
        if meta is None:
            continue
        if meta.flat is not None:
            out += _flat_options(f.name, meta)
            continue
        kind, many = _kind(hints[f.name])
        default = f.default_factory() if f.default_factory is not MISSING else f.default
        required = default is MISSING
        name = (meta.flag or f.name).lstrip("-").replace("-", "_")
        out.append(Option(name, f.name, kind, many, default, required, meta))
    return out


def _flat_options(name: str, meta: Meta) -> list[Option]:
    flat = meta.flat
    assert flat is not None
    hints = typing.get_type_hints(flat.cls)
    out = []
    for f in dataclasses.fields(flat.cls):
        if flat.only is not None and f.name not in flat.only:
            continue
        kind, many = _kind(hints[f.name])
        sub = Meta(flat.help(f), group=meta.group, flat=flat)
        option = flat.flags.get(f.name, f.name).replace("-", "_")
        out.append(Option(option, f"{name}.{f.name}", kind, many, None, False, sub))
    return out


def add_options(parser: argparse.ArgumentParser, cls: type) -> None:
    """Add one argparse option (or argument) per setting of ``cls``."""
    groups: dict[str, Any] = {}
    for o in options(cls):
        where: Any = parser
        if o.meta.group:
            where = groups.get(o.meta.group) or parser.add_argument_group(o.meta.group)
            groups[o.meta.group] = where
        kw = _argparse_keywords(o)
        if o.meta.positional:
            where.add_argument(o.dest, **kw)
        else:
            names = ([o.meta.short] if o.meta.short else []) + [o.flag]
            where.add_argument(*names, dest=o.dest, **kw)


def _argparse_keywords(o: Option) -> dict[str, Any]:
    m = o.meta
    default = None if o.required else o.default
    if o.switch:
        return {"action": "store_true", "default": default, "help": m.help}
    kw: dict[str, Any] = {"default": default, "help": m.help}
    if not o.late:
        kw["type"] = m.parse or o.kind  # argparse names it in its messages ("invalid int value")
    if m.choices is not None:
        kw["choices"] = m.choices
    if m.const is not None:
        kw.update(nargs="?", const=m.const)
    if o.many:
        kw["default"] = list(default or [])
        if m.repeat and not m.positional:
            kw["action"] = "append"
        else:
            kw["nargs"] = "*"
    if m.positional:
        if not o.required and default is None and not o.many:
            kw["nargs"] = "?"
        return kw
    if o.required:
        kw["required"] = True
    metavar = m.metavar or (("V" if o.late else o.name.upper()) if m.flat else None)
    if metavar:
        kw["metavar"] = metavar
    return kw


def from_namespace(cls: type, ns: argparse.Namespace) -> Any:
    """The settings that parsed options describe (flattened ones: only those given); InputError
    when a value parsed here (:attr:`Option.late`) is not one."""
    from dronecap.errors import InputError

    values: dict[str, Any] = {}
    for o in options(cls):
        value = getattr(ns, o.dest)
        if o.late and isinstance(value, str):  # given as text (a default is typed)
            try:
                value = o.convert(value)
            except ValueError as err:
                raise InputError(str(err) if o.meta.flat else f"{o.label()}: {err}") from None
        if "." in o.dest:
            top, sub = o.dest.split(".", 1)
            if value is not None:
                values.setdefault(top, {})[sub] = value
            else:
                values.setdefault(top, {})
        else:
            values[o.dest] = value
    return cls(**values)


def param_value(opt: Option, value: Any) -> Any:
    """A YAML parameter's value as the option's type (ValueError saying what it must be)."""
    if opt.switch:
        if not isinstance(value, bool):
            raise ValueError("must be true or false")
        return value
    items = value if isinstance(value, list) else [value]
    converted = []
    for v in items:
        try:
            c = opt.convert(str(v))
        except (TypeError, ValueError, argparse.ArgumentTypeError) as err:
            if opt.meta.late and not opt.meta.flat:
                raise ValueError(f"{err}") from None  # the parser says what it must be
            name = getattr(opt.meta.parse or opt.kind, "__name__", "a valid value")
            raise ValueError(f"must be {name}, got {v!r}") from None
        if opt.meta.choices is not None and c not in opt.meta.choices:
            raise ValueError(f"must be one of {list(opt.meta.choices)}, got {v!r}")
        converted.append(c)
    if opt.many:
        return converted
    if len(converted) != 1:
        raise ValueError(f"takes one value, got {value!r}")
    return converted[0]


def params_table(cls: type) -> dict[str, Option]:
    """Pipeline parameter name -> option, for settings class ``cls`` (``workdir`` excluded:
    the runner gives each stage its folder)."""
    return {o.name: o for o in options(cls) if o.dest != "workdir"}


def missing_params(cls: type, given: set[str]) -> list[str]:
    """The required parameters of ``cls`` not in ``given``."""
    return [name for name, o in params_table(cls).items() if o.required and name not in given]


def from_params(cls: type, params: dict[str, Any], workdir: str) -> Any:
    """The settings that pipeline ``params`` (substituted) describe, in folder ``workdir``;
    InputError (one line, naming the parameter) when one is unknown or of the wrong type."""
    from dronecap.errors import InputError

    table = params_table(cls)
    values: dict[str, Any] = {"workdir": workdir}
    for key, value in params.items():
        opt = table.get(key)
        if opt is None:
            raise InputError(f"unknown parameter {key!r} (known: {', '.join(sorted(table))})")
        try:
            converted = param_value(opt, value)
        except ValueError as err:
            raise InputError(f"parameter {key!r} {err}") from None
        if "." in opt.dest:
            top, sub = opt.dest.split(".", 1)
            values.setdefault(top, {})[sub] = converted
        else:
            values[opt.dest] = converted
    missing = missing_params(cls, set(params))
    if missing:
        raise InputError(f"missing parameter {missing[0]!r}")
    return cls(**values)


def check(settings: Any) -> None:
    """InputError (one line naming the option) for the first number out of its bounds."""
    from dronecap.errors import check_option

    for o in options(type(settings)):
        if o.meta.minimum is None and o.meta.maximum is None:
            continue
        value = getattr(settings, o.dest)
        for v in value if o.many else [value]:
            if v is not None:
                check_option(o.label(), v, o.meta.minimum, o.meta.maximum)


def command_line(settings: Any) -> list[str]:
    """The options that give ``settings`` (those differing from the defaults), positionals
    first: what a person types to run the same thing."""
    positional: list[str] = []
    flags: list[str] = []
    for o, value in _given(settings):
        values = [str(v) for v in (value if isinstance(value, list) else [value])]
        if o.meta.positional:
            positional += values
        elif o.switch:
            flags += [o.flag] if value else []
        elif o.many and o.meta.repeat:
            for v in values:
                flags += [o.flag, v]
        else:
            flags += [o.flag, *values]
    return positional + flags


def _given(settings: Any) -> Iterator[tuple[Option, Any]]:
    for o in options(type(settings)):
        if "." in o.dest:
            top, sub = o.dest.split(".", 1)
            over = getattr(settings, top)
            if sub in over:
                yield o, over[sub]
        elif o.dest != "workdir" and getattr(settings, o.dest) != o.default:
            yield o, getattr(settings, o.dest)
