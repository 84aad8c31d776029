"""`sim2act`: a thin front over the flows and the warehouse, one module per command group
(campaign, stack, tasks, bench, data; common: what they share).

argparse, not Typer: the commands are plain functions of a Namespace already, nested sub-commands
and mutually exclusive options are argparse's own, and a bad flag stays one line on stderr (exit 2,
`OneLineParser`) rather than a rich panel. Configs are validated before anything is imported or written:
bad input costs one line.
"""

from __future__ import annotations

import argparse
import os
import sys

# Prefect's server answers 500 while its database does not (a restart, a failover): its client then
# retries with backoff (2, 4, ... 32 s, PREFECT_CLIENT_MAX_RETRIES times) as it does for 502/503, instead
# of failing the campaign. Read when prefect is first imported (below), inherited by every process
# sim2act starts (the stack's servers and deployments, the flow runs).
os.environ.setdefault("PREFECT_CLIENT_RETRY_EXTRA_CODES", "500")

from flows.cli import bench, campaign, data, stack, tasks
from schemas.errors import Sim2ActError

GROUPS = (campaign, stack, tasks, bench, data)  # in the order `sim2act --help` lists their commands


class OneLineParser(argparse.ArgumentParser):
    """argparse's parser whose refusal is one line (argparse prints the command's whole usage first: 6 to 9
    lines for one bad flag), naming the command, what is wrong and where the usage is. Every sub-command's
    parser is one too (argparse makes them of their parent's class)."""

    def error(self, message: str):
        self.exit(2, f"{self.prog}: error: {message} (usage: {self.prog} --help)\n")

    def parse_args(self, args=None, namespace=None):
        """argparse's, with flags no command takes refused by the command they were given to: argparse
        refuses them from the top parser, whose usage does not list the command's flags."""
        parsed, extras = self.parse_known_args(args, namespace)
        if extras:
            command = getattr(parsed, "command_prog", self.prog)
            self.exit(2, f"{command}: error: unrecognized arguments: {' '.join(extras)} (usage: {command} --help)\n")
        return parsed


def _name_commands(parser: argparse.ArgumentParser) -> None:
    """Each command's parser records its name (`command_prog`) in what it parses."""
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for sub in action.choices.values():
                sub.set_defaults(command_prog=sub.prog)
                _name_commands(sub)


def build_parser() -> argparse.ArgumentParser:
    parser = OneLineParser(prog="sim2act", description=__doc__.splitlines()[0].replace("`", ""))
    commands = parser.add_subparsers(dest="command", required=True)
    for group in GROUPS:
        group.register(commands)
    _name_commands(parser)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Run one command. A known failure (any Sim2ActError) is one line on stderr and exit status 2."""
    argv = sys.argv[1:] if argv is None else argv
    args = build_parser().parse_args(argv)
    args.command_line = " ".join(["sim2act", *argv])  # reports say the command that made them
    try:
        from schemas.settings import apply_secrets_file

        apply_secrets_file()  # every command: the shard store's keys are read by sql, export, replay as well
        status = args.handler(args)
        sys.stdout.flush()  # a reader gone is found here, not in the interpreter's exit (a traceback there)
        return status
    except BrokenPipeError:
        if not _stdout_gone():
            raise  # another pipe than stdout (a worker's, a server's): not the reader going away
        # the reader stopped reading (`sim2act tasks list | head`): quiet, as a tool killed by SIGPIPE is;
        # stdout pointed at /dev/null so that the interpreter's last flush does not fail again
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 1
    except Sim2ActError as exc:
        print(f"sim2act: {exc.label}{exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("sim2act: interrupted; run the same command again to resume", file=sys.stderr)
        return 130
    except Exception as exc:
        said = _server_failure(exc)
        if said is None:
            raise
        print(f"sim2act: {said}", file=sys.stderr)
        return 2


def _stdout_gone() -> bool:
    """stdout is a pipe whose reader closed it (poll says POLLERR on its write end)."""
    import select

    try:
        poller = select.poll()
        poller.register(sys.stdout.fileno(), select.POLLOUT)
        return any(event & select.POLLERR for _, event in poller.poll(0))
    except (OSError, ValueError, AttributeError):  # no file descriptor (a test's capture), or no poll
        return False


def _server_failure(exc: BaseException) -> str | None:
    """A Prefect server that kept failing past its client's retries (its database down longer than
    ~1 min): one line; the units done so far are registered, so the same command resumes."""
    if "prefect" not in sys.modules:
        return None
    from prefect.exceptions import PrefectHTTPStatusError

    # the temporary server killed (or dead) while it started, before `ends_with_its_server` could follow it:
    # Prefect's client raises a bare RuntimeError after waiting for it
    cause = exc
    while cause is not None:
        if isinstance(cause, RuntimeError) and "ephemeral Prefect API server" in str(cause):
            if "exited with code" in str(cause):
                code = str(cause).rsplit("exited with code", 1)[-1].strip(" .")
                what = f"died while it started (exit {code})"
            else:  # alive but not answering in Prefect's wait: a machine too loaded, most likely
                what = "did not answer while it started"
            return (f"Prefect's temporary API server {what}; nothing ran against it. "
                    "Run the same command again to resume (finished units are kept)")
        cause = cause.__cause__ or cause.__context__

    while exc is not None and not isinstance(exc, PrefectHTTPStatusError):
        exc = exc.__cause__ or exc.__context__
    if exc is None:
        return None
    request = exc.request
    return (f"the Prefect server answered {exc.response.status_code} to {request.method} {request.url.path} "
            f"after its client's retries: check the server and its database, then run the same command again "
            f"to resume")
