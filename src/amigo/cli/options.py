"""Click option types shared by several commands."""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import click


class ManyValues(click.Option):
    """An option that takes every following argument up to the next option, so that
    ``--sci a.fits b.fits --cal c.fits`` works (shell globs expand to several words after
    one flag); it can also be repeated (``--sci a.fits --sci b.fits``). A value that
    starts with ``-`` ends the list, as an option does."""

    def __init__(self, param_decls: Sequence[str] | None = None, **kwargs: Any) -> None:
        super().__init__(param_decls, multiple=True, **kwargs)

    def add_to_parser(self, parser: Any, ctx: click.Context) -> None:
        super().add_to_parser(parser, ctx)
        for name in self.opts:
            option = parser._long_opt.get(name) or parser._short_opt.get(name)
            if option is None:
                continue
            previous = option.process

            def process(value: Any, state: Any, _previous: Any = previous) -> None:
                _previous(value, state)
                while state.rargs and not state.rargs[0].startswith("-"):
                    _previous(state.rargs.pop(0), state)

            option.process = process
