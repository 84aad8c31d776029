"""The one base of every error a user can cause or fix: `sim2act` turns any of them into one line
on stderr (exit status 2), never a traceback. Each error keeps its Python base too (a ConfigError
is still a ValueError), so library callers catch what they always caught."""

from __future__ import annotations


class Sim2ActError(Exception):
    """A known failure, said in one line: what is wrong and, where it helps, what to do."""

    label = ""  # the line's prefix after "sim2act: ", e.g. "config error: "
