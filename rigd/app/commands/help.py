"""One look for every `rigd ... --help`: flags without a value placeholder, values and arguments
as upper-case placeholders (PATH, FLOAT, TAKE, IMAGES...), the same in the usage line and the
option table.

Typer labels each parameter with its Python annotation (`--json <bool>`, `<list[Path]>`) and
wraps required arguments in braces in the usage line (`{take}`); a user should not have to read
Python types. Every command and group of the CLI is built from `RigdTyper`, whose command and
group classes rewrite the placeholders when click asks for the parameters.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import typer
from typer.core import TyperArgument, TyperCommand, TyperGroup, TyperOption

if TYPE_CHECKING:
    from typer._click.core import Command, Context, Parameter  # the click typer builds on (its own copy)

#: Typer's type labels (without the angle brackets) -> the placeholder shown.
_PLACEHOLDERS = {"str": "TEXT", "int": "INT", "float": "FLOAT", "path": "PATH", "bool": "BOOL"}


class _Argument(TyperArgument):
    """An argument named by its placeholder alone: `TAKE`, `[TAKE]`, `IMAGES...`."""

    def display_type_rich(self, ctx: Context) -> str | None:
        return None

    def _usage_display_name(self) -> str:
        name = self.display_name_raw
        if not self.required:
            name = f"[{name}]"
        return name + ("..." if self.nargs != 1 else "")

    def _rich_display_name(self) -> str:
        return self.display_name_raw + ("..." if self.nargs != 1 else "")


def placeholder(option: TyperOption, ctx: Context) -> str:
    """The placeholder of an option's value: a flag has none, a choice lists its values."""
    if option.is_flag or option.count:
        return ""
    label = option.display_type(ctx).strip("<>").removeprefix("list[").removesuffix("]")
    if "|" in label:
        return f"[{label}]"
    return _PLACEHOLDERS.get(label.lower(), label.upper())


def tidy_params(params: list[Parameter], ctx: Context) -> list[Parameter]:
    """Set every parameter's placeholder (once; click builds a command's parameters once)."""
    for param in params:
        if isinstance(param, TyperArgument):
            if not isinstance(param, _Argument):
                param.__class__ = _Argument
            param.metavar = (param.metavar or param.name or "ARG").upper()
        elif isinstance(param, TyperOption) and param.metavar is None:
            param.metavar = placeholder(param, ctx)
    return params


class RigdCommand(TyperCommand):
    def get_params(self, ctx: Context) -> list[Parameter]:
        return tidy_params(super().get_params(ctx), ctx)


class RigdGroup(TyperGroup):
    def get_params(self, ctx: Context) -> list[Parameter]:
        return tidy_params(super().get_params(ctx), ctx)

    def get_command(self, ctx: Context, cmd_name: str) -> Command | None:
        """A sub-command or sub-group, with rigd's placeholders even when it was made by a plain
        `typer.Typer` (a command registered from another package)."""
        cmd = super().get_command(ctx, cmd_name)
        if type(cmd) is TyperCommand:
            cmd.__class__ = RigdCommand
        elif type(cmd) is TyperGroup:
            cmd.__class__ = RigdGroup
        return cmd


class RigdTyper(typer.Typer):
    """A Typer whose commands and groups show `rigd`'s placeholders (see the module docstring)."""

    def __init__(self, **kwargs: Any) -> None:
        kwargs.setdefault("cls", RigdGroup)
        super().__init__(**kwargs)

    def command(self, *args: Any, **kwargs: Any) -> Any:
        kwargs.setdefault("cls", RigdCommand)
        return super().command(*args, **kwargs)
