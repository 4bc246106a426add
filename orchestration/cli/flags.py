"""Command-line flags generated from config dataclasses (cleanrl style: one typed config per program).

Each leaf field of a config, nested configs included, becomes one `--flag-name`; flag names are the
field names, so they must be unique across the nesting (checked). The help text is the field's
docstring, the string literal written under it in the class body. The flags record which of them were
given (`given_flags`): a value the user typed is told apart from a default even when the two are equal.
"""

from __future__ import annotations

import argparse
import ast
import dataclasses
import functools
import inspect
import textwrap
import types
import typing
from typing import Any

from rllock.config import nested_config


@functools.cache
def field_docs(cls: type) -> dict[str, str]:
    """{field name: its docstring} of a dataclass, read from its source (none where it is not installed)."""
    try:
        tree = ast.parse(textwrap.dedent(inspect.getsource(cls)))
    except OSError:
        return {}
    body = tree.body[0].body  # type: ignore[attr-defined]
    docs = {}
    for node, after in zip(body, body[1:]):
        if (
            isinstance(node, ast.AnnAssign)
            and isinstance(node.target, ast.Name)
            and isinstance(after, ast.Expr)
            and isinstance(after.value, ast.Constant)
            and isinstance(after.value.value, str)
        ):
            docs[node.target.id] = " ".join(after.value.value.split())
    return docs


def leaves(cls: type, prefix: tuple[str, ...] = ()) -> list[tuple[tuple[str, ...], dataclasses.Field, type]]:
    """(path, field, owner class) of every leaf field, depth first."""
    out = []
    for f in dataclasses.fields(cls):
        sub = nested_config(f)
        if sub is not None:
            out.extend(leaves(sub, (*prefix, f.name)))
        else:
            out.append(((*prefix, f.name), f, cls))
    return out


def _leaf_type(owner: type, name: str) -> Any:
    hint = typing.get_type_hints(owner)[name]
    args = [a for a in typing.get_args(hint) if a is not type(None)]
    return args[0] if typing.get_origin(hint) in (typing.Union, types.UnionType) else hint


_GIVEN = "_flags_given"


def _record(namespace: argparse.Namespace, dest: str) -> None:
    setattr(namespace, _GIVEN, getattr(namespace, _GIVEN, frozenset()) | {dest})


class _Given(argparse.Action):
    """Stores the flag's value and records that it was given."""

    def __call__(self, parser, namespace, values, option_string=None) -> None:
        setattr(namespace, self.dest, values)
        _record(namespace, self.dest)


class _GivenBool(argparse.BooleanOptionalAction):
    """--flag / --no-flag, recording that one of them was given."""

    def __call__(self, parser, namespace, values, option_string=None) -> None:
        super().__call__(parser, namespace, values, option_string)
        _record(namespace, self.dest)


def given_flags(args: argparse.Namespace) -> frozenset[str]:
    """The leaf field names whose flags were given on the command line (flags made by `add_flags`)."""
    return getattr(args, _GIVEN, frozenset())


def _int_tuple(text: str) -> tuple[int, ...]:
    try:
        return tuple(int(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated integers, got {text!r}") from None


def add_flags(
    parser: argparse.ArgumentParser,
    cls: type,
    *,
    required_unless: str | None = None,
    choices: dict[str, tuple[str, ...]] | None = None,
) -> None:
    """One flag per leaf field of `cls`. Fields without a default get `default=None` and the note
    'required unless `required_unless`' (checked by the caller)."""
    seen: set[str] = set()
    for path, f, owner in leaves(cls):
        name = path[-1]
        if name in seen:
            raise ValueError(f"two config fields are called {name!r}: flags must be unique")
        seen.add(name)
        flag = "--" + name.replace("_", "-")
        doc = field_docs(owner).get(name, "").replace("%", "%%")  # argparse formats help with %
        kind = _leaf_type(owner, name)
        default = (
            f.default
            if f.default is not dataclasses.MISSING
            else (f.default_factory() if f.default_factory is not dataclasses.MISSING else None)
        )
        if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
            note = f" (required unless {required_unless})" if required_unless else " (required)"
            parser.add_argument(flag, type=kind, default=None, action=_Given, help=doc + note)
        elif kind is bool:
            parser.add_argument(flag, default=default, action=_GivenBool, help=doc)
        elif typing.get_origin(kind) is tuple:
            assert isinstance(default, tuple)
            parser.add_argument(
                flag,
                type=_int_tuple,
                default=default,
                action=_Given,
                help=f"{doc} Comma-separated (default {','.join(map(str, default))}).",
            )
        else:
            shown = "" if default is None else f" (default {default})"
            parser.add_argument(
                flag,
                type=kind,
                default=default,
                choices=(choices or {}).get(name),
                action=_Given,
                help=doc + shown,
            )


def from_flags(cls: type, args: argparse.Namespace) -> Any:
    """The config of class `cls` from parsed flags (nested configs built from their own fields)."""
    values = {}
    for f in dataclasses.fields(cls):
        sub = nested_config(f)
        values[f.name] = from_flags(sub, args) if sub is not None else getattr(args, f.name)
    return cls(**values)
