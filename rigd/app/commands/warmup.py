"""`rigd warmup`: compile the capture path's kernels now, not during the first take."""

from __future__ import annotations

from typing import Annotated

import typer
from rich.markup import escape

from rigd.app.commands.consoles import fail, stderr_console
from rigd.core.errors import RigdError

console = stderr_console()


def warmup(
    force: Annotated[
        bool, typer.Option("--force", help="Warm up even when numba's cache already holds every kernel.")
    ] = False,
) -> None:
    """Compile every kernel the default rig runs into numba's cache (tens of seconds on a fresh
    install; `rigd capture` does it itself on a cold cache)."""
    from rigd.app.warmup import is_warm, stamp_path

    if not force and is_warm():
        console.print(f"warm-up: numba's cache holds every kernel of the capture path ({stamp_path()})")
        return
    run_warmup("compiling the capture path's kernels")


def run_warmup(why: str, *, required: bool = True) -> None:
    """The warm-up with its progress lines on stderr: one when it starts, one per kernel compiled
    and a last one with the count and the seconds it took. A warm-up that fails ends the command
    when `required`; otherwise (before a capture, whose devices' preflight still compiles what
    each runs) it is said on one line and the command goes on."""
    from rigd.app.warmup import warm_up

    console.print(f"warm-up: {why} (a take of the sim rig in virtual time, then thrown away)...")
    count = 0

    def on_kernel(name: str, seconds: float) -> None:
        nonlocal count
        count += 1
        console.print(f"warm-up: [{count}] {escape(name)} compiled in {seconds:.1f} s", highlight=False)

    try:
        result = warm_up(on_kernel)
    except RigdError as exc:
        if required:
            raise fail(exc) from exc
        console.print(
            f"[yellow]warm-up failed, capturing without it:[/] {escape(str(exc))}",
            soft_wrap=True,
            highlight=False,
        )
        return
    where = f", listed in {result.stamp}" if result.stamp else ""
    console.print(
        f"warm-up: done in {result.seconds:.1f} s: {len(result.compiled)} kernels compiled, "
        f"{len(result.kernels)} cached{where}",
        highlight=False,
    )
