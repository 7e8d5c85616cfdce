"""The docs' commands and paths are the code's: a flag, node parameter, launch argument,
executable, file or test that the docs name and the code does not have fails here.

Read: README.md and docs/*.md (not docs/results.md, not docs/results/). Extracted:

- the shell commands of their fenced code blocks (``bash``/``sh``/``shell``; ``$`` lines of
  ``console``; lines of an unlabelled block that start with a checked program): a trailing
  backslash continues a line, ``# comments`` are dropped, and ``&&``, ``;``, ``|``, ``&``
  separate commands (``sh -c '...'`` is read inside);
- the backticked commands of the prose (``hdrqn ...``, ``ros2 ...``, ``python -m ...``,
  ``scripts/...``), and its backticked repository paths and relative links.

Checked:

- ``hdrqn ...`` of a code block: parsed by the real parser (:func:`hdrqn_ros.cli.build_parser`),
  so its subcommand, flags and their values exist; a usage synopsis (``[--flag X]``) and the
  prose's ``hdrqn ...`` have their subcommands and flags looked up. :data:`SKIPS` lists the
  few left out, each with its reason.
- :data:`RUN_FULLY`: a handful of documented commands run in-process (:func:`hdrqn_ros.cli.main`)
  in a temporary folder, placeholders filled and budgets cut (:data:`BUDGET_CUTS`): exit 0.
- ``ros2 run hdrqn_ros EXE``, ``python -m hdrqn_ros.nodes.MODULE``, ``ros2 launch hdrqn_ros
  FILE``, ``ros2 param get /NODE NAME``: the executable is a console script of setup.py and
  a node of :data:`~hdrqn_ros.nodes.executables.NODES` (a ``python -m`` module runs its node:
  it has a ``__main__`` block); each launch argument is declared by the launch file
  (``DeclareLaunchArgument("name"``); each ``-p`` parameter is declared by the node (its
  ``PARAMETERS``, as docs/topics.md's tables; needs rclpy).
- ``python -m hdrqn_ros.X`` (not a node): the module exists and has a ``__main__`` block.
- ``scripts/X`` and ``[python] benchmarks/X.py``: the file exists and names each ``--flag``.
- paths: each backticked repository path of the prose (``agents/x.py`` is under hdrqn_ros/,
  ``test_x.py::name`` under test/), each relative link and each repository path of a
  command exists (not ``runs/``, ``/tmp``, ``~`` or paths with placeholders; the commands'
  made-up outputs are :data:`EXAMPLE_OUTPUTS`); ``file.py::name`` names a test there.
- the ``from hdrqn_ros... import name`` of the python code blocks import.
- docs/topics.md's sample ``ros2 topic list`` is the training graph's topics (needs rclpy).
- every command's program is one checked above or one of :data:`OTHER_PROGRAMS`, so that a new
  kind of command is noticed rather than passed over.

Each check is also tried on a scratch doc naming a flag, subcommand, executable, launch
argument, parameter, module, path and test that do not exist (the last tests).
"""
from __future__ import annotations

import argparse
import ast
import contextlib
import functools
import importlib
import importlib.util
import io
import re
import shlex
from dataclasses import dataclass, field
from pathlib import Path

import pytest

from hdrqn_ros.cli import build_parser, main
from hdrqn_ros.nodes.executables import NODES

from conftest import NEEDS_RCLPY
from test_launch_files import console_scripts

ROOT = Path(__file__).resolve().parents[1]
DOCS = (ROOT / "README.md", *sorted(p for p in (ROOT / "docs").glob("*.md") if p.name != "results.md"))
"""The docs read: docs/results.md and docs/results/ are records of runs, not instructions."""
TOP_FOLDERS = ("hdrqn_ros", "config", "test", "benchmarks", "scripts", "docs", "launch", "policies", "bags",
               "ros_interfaces")
"""A backticked token under one of these (or ``README.md``) is a repository path to check."""
SHELL_LANGS = {"bash", "sh", "shell"}
CHECKED_PROGRAMS = ("hdrqn", "ros2", "python", "python3")
"""The first words that make a line of an unlabelled code block (or the prose) a command."""
OTHER_PROGRAMS = {"pip", "cd", "git", "colcon", "source", "export", "ray", "yes", "unshare", "ip", "kill"}
"""Programs of the docs' commands that this test does not check (installing, the shell, Ray's
own CLI, the CPU hog): any other program fails ``test_every_command_is_checked``."""
OTHER_ROS2 = {"topic", "node", "bag", "security", "interface", "service", "action", "lifecycle"}
"""``ros2`` verbs of ROS's own tools (on topics and names of the running graph, not checked here)."""

SKIPS = {
    ("README.md", "hdrqn COMMAND --help"): "COMMAND stands for any subcommand (test_hdrqn_help_of_every_subcommand)",
}
"""(doc, command as written) -> why it is not checked. A skip that matches no command fails."""

EXAMPLE_OUTPUTS = {"bags/run1", "bags/run2", "bags/v2-run", "bags/v2-policy", "docs/img/reliability.png"}
"""Repository-looking paths that the docs' commands write (or stand for a user's own bag):
not expected to exist."""


# -- extraction ---------------------------------------------------------------------------------
@dataclass(frozen=True)
class Command:
    """One command of a doc: where it is, its words (placeholders as written), and whether it
    is in a code block (else backticked prose)."""
    doc: str
    line: int
    argv: tuple[str, ...]
    fenced: bool = True

    @property
    def text(self) -> str:
        return " ".join(self.argv)

    def __str__(self) -> str:
        return f"{self.doc}:{self.line}: {self.text}"


FENCE = re.compile(r"^\s*(```+|~~~+)\s*([\w+-]*)")


def fenced_blocks(text: str) -> list[tuple[str, list[tuple[int, str]]]]:
    """(info string, [(line number, line)]) of each fenced code block of a markdown text."""
    blocks, current, fence, lang = [], None, None, ""
    for number, line in enumerate(text.splitlines(), 1):
        match = FENCE.match(line)
        if current is None and match:
            current, fence, lang = [], match.group(1), match.group(2).lower()
        elif current is not None and line.strip().startswith(fence) and not line.strip().strip(fence[0]):
            blocks.append((lang, current))
            current = None
        elif current is not None:
            current.append((number, line))
    return blocks


def prose_lines(text: str) -> list[tuple[int, str]]:
    """The lines of a markdown text outside its fenced code blocks."""
    inside = {number for _, block in fenced_blocks(text) for number, _ in block}
    out = []
    for number, line in enumerate(text.splitlines(), 1):
        if number in inside:
            continue
        if FENCE.match(line):  # a fence line itself
            continue
        out.append((number, line))
    return out


def logical_lines(block: list[tuple[int, str]]) -> list[tuple[int, str]]:
    """(first line number, text) with backslash continuations joined."""
    out, pending, start = [], "", None
    for number, line in block:
        start = number if start is None else start
        if line.rstrip().endswith("\\"):
            pending += line.rstrip()[:-1] + " "
            continue
        out.append((start, pending + line))
        pending, start = "", None
    if start is not None:
        out.append((start, pending))
    return out


def split_commands(line: str) -> list[list[str]]:
    """The simple commands of a shell line: words as the shell splits them, ``# comments``
    dropped, separated at ``&&``, ``||``, ``;``, ``|``, ``&``; ``sh -c 'LINE'`` is read inside."""
    lexer = shlex.shlex(line, posix=True, punctuation_chars=";&|")
    lexer.whitespace_split = True
    commands, words = [], []
    for word in lexer:
        if word and set(word) <= set(";&|"):
            commands.append(words)
            words = []
        else:
            words.append(word)
    commands.append(words)
    out = []
    for words in filter(None, commands):
        shell = next((i for i in range(len(words) - 2) if words[i:i + 2] == ["sh", "-c"]), None)
        if shell is not None:  # `unshare -n sh -c 'LINE'`: the outer words, then LINE's commands
            out += [words[:shell]] if shell else []
            out += split_commands(words[shell + 2])
        else:
            out.append(words)
    return out


def block_commands(lang: str, block: list[tuple[int, str]]) -> list[tuple[int, list[str]]]:
    """(line, words) of each command of a code block; nothing from a block of another language."""
    if lang == "console":
        block = [(n, line.strip()[2:]) for n, line in block if line.strip().startswith("$ ")]
    elif lang and lang not in SHELL_LANGS:
        return []
    out = []
    for number, line in logical_lines(block):
        for words in split_commands(line):
            if lang or words[0] in CHECKED_PROGRAMS or words[0].startswith(("scripts/", "./scripts/")):
                out.append((number, words))
    return out


BACKTICKED = re.compile(r"`([^`]+)`")
LINK = re.compile(r"\]\(([^)\s]+)\)")
BLOCK_START = re.compile(r"^\s*([-*+] |\d+\. |#|\|)")
"""A line that starts a markdown block (list item, heading, table row): no code span crosses it."""


def prose_blocks(text: str) -> list[tuple[int, str]]:
    """(first line, text) of each paragraph, list item, heading or table row of the prose: a
    backticked span may continue on the next line of its block."""
    blocks, last = [], None
    for number, line in prose_lines(text):
        joins = blocks and last == number - 1 and line.strip() and blocks[-1][1].strip() \
            and not BLOCK_START.match(line) and not blocks[-1][1].lstrip().startswith("|")
        if joins:
            blocks[-1] = (blocks[-1][0], blocks[-1][1] + "\n" + line)
        else:
            blocks.append((number, line))
        last = number
    return blocks


def backticked(text: str) -> list[tuple[int, str]]:
    """(line, span) of each backticked span of the prose, a span broken over lines joined."""
    out = []
    for first, block in prose_blocks(text):
        for match in BACKTICKED.finditer(block):
            out.append((first + block.count("\n", 0, match.start()), " ".join(match.group(1).split())))
    return out


def prose_commands(doc: str, text: str) -> list[Command]:
    """The backticked commands of the prose: ``hdrqn ...``, ``ros2 run/launch/param ...``,
    ``python -m hdrqn_ros...``, ``scripts/...``, ``benchmarks/X.py ...``."""
    out = []
    for number, token in backticked(text):
        words = token.split()
        if (words[0] == "hdrqn"
                or (words[:2] in (["ros2", "run"], ["ros2", "launch"], ["ros2", "param"]) and len(words) > 2)
                or (words[:2] == ["python", "-m"] and len(words) > 2 and words[2].startswith("hdrqn_ros."))
                or (words[0].startswith(("scripts/", "benchmarks/")) and len(words) > 1)):
            out.append(Command(doc, number, tuple(words), fenced=False))
    return out


def relative(path: Path) -> str:
    return path.relative_to(ROOT).as_posix()


@functools.cache
def all_commands() -> tuple[Command, ...]:
    """Every command of the docs, code blocks first, then the prose's."""
    out = []
    for path in DOCS:
        text = path.read_text(encoding="utf-8")
        for lang, block in fenced_blocks(text):
            out += [Command(relative(path), n, tuple(words)) for n, words in block_commands(lang, block)]
        out += prose_commands(relative(path), text)
    return tuple(out)


def executable_of_module(module: str) -> str | None:
    """The node executable that ``python -m hdrqn_ros.nodes.MODULE`` starts."""
    for executable, entry in NODES.items():
        if module in (executable, entry.partition(":")[0]):
            return executable
    return None


def kind(command: Command) -> str:
    """hdrqn, ros (a node/launch/param of this package), module (``python -m`` of another
    module of the package), script, other-ros, other or unknown."""
    argv = command.argv
    program = argv[0].removeprefix("./")
    if program == "hdrqn":
        return "hdrqn"
    if program == "ros2" and len(argv) > 2 and argv[1] in ("run", "launch"):
        return "ros" if argv[2] == "hdrqn_ros" else "other-ros"
    if program == "ros2" and len(argv) > 1 and argv[1] == "param":
        return "ros"
    if program == "ros2" and len(argv) > 1 and argv[1] in OTHER_ROS2:
        return "other-ros"
    if program in ("python", "python3") and len(argv) > 2 and argv[1] == "-m" and argv[2].startswith("hdrqn_ros."):
        node_module = argv[2].startswith("hdrqn_ros.nodes.") and executable_of_module(argv[2].rsplit(".", 1)[-1])
        return "ros" if node_module else "module"
    if program in ("python", "python3") and len(argv) > 1 and argv[1].startswith(("benchmarks/", "scripts/")):
        return "script"
    if program.startswith(("scripts/", "benchmarks/")):
        return "script"
    if program in OTHER_PROGRAMS:
        return "other"
    return "unknown"


def commands_of(*kinds: str) -> list[Command]:
    return [c for c in all_commands() if kind(c) in kinds and (c.doc, c.text) not in SKIPS]


def ids(commands) -> list[str]:
    return [f"{c.doc}:{c.line}:{' '.join(c.argv[:4])}" for c in commands]


# -- hdrqn: the real argument parser ------------------------------------------------------------
def is_placeholder(word: str) -> bool:
    """An upper-case word that stands for a value (RUN, NAME, COMMAND, BAG_DIR...)."""
    return bool(re.fullmatch(r"[A-Z][A-Z0-9_]*(\.\.\.)?", word))


def parse_problem(argv: list[str] | tuple[str, ...]) -> str | None:
    """What the real parser says about ``hdrqn ARGV`` (None: it parses; --help counts)."""
    err = io.StringIO()
    try:
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
            build_parser().parse_args(list(argv[1:]))
    except SystemExit as exc:
        if exc.code not in (0, None):
            return (err.getvalue().strip().splitlines() or [f"exit {exc.code}"])[-1]
    return None


def _subparsers(parser: argparse.ArgumentParser):
    """The parser's subcommands action (``choices``: name -> parser), or None."""
    return next((a for a in parser._actions if isinstance(a, argparse._SubParsersAction)), None)


def flag_problems(argv: list[str] | tuple[str, ...]) -> list[str]:
    """The subcommands and ``--flags`` of ``hdrqn ...`` (a synopsis or prose) that the parser
    lacks; words that are not flags after the subcommands are not looked at."""
    parser, problems = build_parser(), []
    for word in argv[1:]:
        word = word.strip("[]")
        sub = _subparsers(parser)
        if re.match(r"--\w|-[A-Za-z]$", word):  # not a negative number
            flag = word.split("=")[0]
            if flag not in parser._option_string_actions:
                problems.append(f"{parser.prog} has no flag {flag}")
        elif sub is not None and not is_placeholder(word):
            names = word.split("/")  # `hdrqn train/eval/export`
            problems += [f"{parser.prog} has no subcommand {name!r}" for name in names if name not in sub.choices]
            if len(names) > 1 or names[0] not in sub.choices:
                break
            parser = sub.choices[word]
        elif sub is not None:
            problems.append(f"{word}: a placeholder where a subcommand of {parser.prog} goes (fill it, or add "
                            "the command to SKIPS)")
            break
    return problems


def hdrqn_problems(command: Command) -> list[str]:
    """A code block's command parses; a synopsis' or the prose's flags and subcommands exist."""
    synopsis = any(word.startswith("[") for word in command.argv)
    if command.fenced and not synopsis:
        problem = parse_problem(command.argv)
        return [problem] if problem else []
    return flag_problems(command.argv)


@pytest.mark.parametrize("command", commands_of("hdrqn"), ids=ids(commands_of("hdrqn")))
def test_hdrqn_command_parses(command):
    problems = hdrqn_problems(command)
    assert not problems, f"{command}: {'; '.join(problems)}"


def test_hdrqn_help_of_every_subcommand():
    """README's ``hdrqn COMMAND --help``, for each COMMAND."""
    commands = _subparsers(build_parser()).choices
    assert {name: parse_problem(("hdrqn", name, "--help")) for name in commands} == dict.fromkeys(commands)


# -- a few commands run fully -------------------------------------------------------------------
TINY_TRAIN = ("--set", "num_envs=2", "--set", "learning_starts=0", "--set", "eval_every=0", "--no-progress")
BUDGET_CUTS = {"--episodes": "2", "--num-envs": "2", "--updates": "2"}
"""Flag -> the value a fully run command gets instead of the documented one."""


@dataclass(frozen=True)
class FullRun:
    """A documented command run fully: the first command of ``doc`` that begins with
    ``begins``, its words replaced by ``fill`` (a word, or the start of a path: ``{tmp}`` is the
    temporary folder), ``BUDGET_CUTS`` applied and ``extra`` appended; ``after``: the runs
    whose outputs it reads."""
    doc: str
    begins: str
    fill: dict = field(default_factory=dict)
    extra: tuple[str, ...] = ()
    after: tuple[str, ...] = ()


RUN_FULLY = {
    "help": FullRun("README.md", "hdrqn --help"),
    "envs": FullRun("docs/training.md", "hdrqn envs"),
    "train": FullRun("docs/recording.md", "hdrqn train --episodes 2000 --out runs/v2 --record bags/v2-run",
                     {"runs/v2": "{tmp}/v2", "bags/v2-run": "{tmp}/v2-run"}, TINY_TRAIN),
    "eval": FullRun("docs/recording.md", "hdrqn eval --checkpoint runs/v2/checkpoints/last.pt",
                    {"runs/v2": "{tmp}/v2", "bags/v2-policy": "{tmp}/v2-policy"}, after=("train",)),
    "values": FullRun("docs/training.md", "hdrqn values RUN", {"RUN": "{tmp}/v2"}, after=("train",)),
    "plot": FullRun("README.md", "hdrqn plot runs/NAME", {"runs/NAME": "{tmp}/v2"}, after=("train",)),
    "export": FullRun("docs/deploy.md", "hdrqn export --checkpoint RUN/checkpoints/last.pt",
                      {"RUN": "{tmp}/v2", "policy/": "{tmp}/policy"}, after=("train",)),
    "eval-policy": FullRun("docs/deploy.md", "hdrqn eval --policy policy/", {"policy/": "{tmp}/policy"},
                           after=("export",)),
    "bag-info": FullRun("docs/recording.md", "hdrqn bag info bags/hdrqn-v2_gridworld-2goals --json"),
    "offline": FullRun("docs/recording.md", "hdrqn train --from-bag bags/hdrqn-v2_gridworld-2goals",
                       {"runs/offline": "{tmp}/offline"}, ("--no-progress",)),
}
"""The commands run fully (in this order when run together), each under a second or a few."""


def documented(run: FullRun, commands=None) -> Command:
    """The documented command that ``run`` is."""
    commands = all_commands() if commands is None else commands
    found = [c for c in commands if c.doc == run.doc and c.text.startswith(run.begins)]
    assert found, f"{run.doc} has no command beginning `{run.begins}` any more: update RUN_FULLY"
    return found[0]


def filled(argv, fill: dict, tmp: Path) -> list[str]:
    """``argv`` with each word (or path start) of ``fill`` replaced, the repository's own paths
    made absolute and the budgets cut."""
    out = []
    for word in argv:
        for key, value in sorted(fill.items(), key=lambda kv: -len(kv[0])):
            if word == key or word.startswith(key.rstrip("/") + "/"):
                word = value.format(tmp=tmp) + word[len(key.rstrip("/")):]
                break
        else:
            if word.split("/")[0] in TOP_FOLDERS and (ROOT / word).exists():
                word = str(ROOT / word)
        if out and out[-1] in BUDGET_CUTS:
            word = BUDGET_CUTS[out[-1]]
        out.append(word)
    return out


def run_hdrqn(argv: list[str], cwd: Path) -> tuple[int, str]:
    """``hdrqn ARGV`` in-process in ``cwd``: (exit code, stdout and stderr)."""
    output = io.StringIO()
    with contextlib.chdir(cwd), contextlib.redirect_stdout(output), contextlib.redirect_stderr(output):
        try:
            code = main(argv)
        except SystemExit as exc:
            code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 2)
    return code, output.getvalue()


class Sandbox:
    """A temporary folder where the :data:`RUN_FULLY` commands run, each once, after those
    it reads."""

    def __init__(self, tmp: Path):
        self.tmp, self.results = tmp, {}

    def run(self, name: str, runs=None) -> tuple[int, str, list[str]]:
        runs = RUN_FULLY if runs is None else runs
        if name not in self.results:
            full = runs[name]
            for before in full.after:
                code, output, argv = self.run(before, runs)
                assert code == 0, f"{before} (needed by {name}) failed: hdrqn {' '.join(argv)}\n{output[-3000:]}"
            argv = filled(documented(full).argv[1:], full.fill, self.tmp) + list(full.extra)
            code, output = run_hdrqn(argv, self.tmp)
            self.results[name] = (code, output, argv)
        return self.results[name]


@pytest.fixture(scope="module")
def sandbox(tmp_path_factory):
    return Sandbox(tmp_path_factory.mktemp("docs-commands"))


@pytest.mark.parametrize("name", list(RUN_FULLY))
def test_documented_command_runs(name, sandbox):
    command = documented(RUN_FULLY[name])
    code, output, argv = sandbox.run(name)
    assert code == 0, f"{command}\nran as: hdrqn {' '.join(argv)}\nexit {code}:\n{output[-3000:]}"


# -- ROS: executables, launch arguments, parameters ---------------------------------------------
@dataclass
class RosUse:
    """What a ROS command names: an executable (None for a launch), a launch file, launch
    arguments, parameters, its own arguments before --ros-args and paths it reads."""
    executable: str | None = None
    launch_file: str | None = None
    launch_args: list = field(default_factory=list)
    parameters: list = field(default_factory=list)
    own_args: list = field(default_factory=list)
    module: str | None = None
    problems: list = field(default_factory=list)


def ros_use(argv: tuple[str, ...]) -> RosUse:
    """Read a ``ros2 run/launch/param`` or ``python -m hdrqn_ros.nodes.X`` command."""
    use = RosUse()
    if argv[0] == "ros2" and argv[1] == "param":
        if len(argv) > 3 and argv[2] in ("get", "set", "describe"):
            use.executable = argv[3].rstrip("/").rsplit("/", 1)[-1]
            use.parameters = [argv[4]] if len(argv) > 4 else []
        return use
    if argv[0] == "ros2" and len(argv) < 4:
        what = "launch file" if argv[1] == "launch" else "executable"
        use.problems.append(f"ros2 {argv[1]} {argv[2]} names no {what}")
        return use
    if argv[0] == "ros2" and argv[1] == "launch":
        use.launch_file = argv[3]
        use.launch_args = [word.split(":=")[0] for word in argv[4:] if ":=" in word]
        return use
    if argv[0] == "ros2":  # ros2 run hdrqn_ros EXE
        use.executable, rest = argv[3], list(argv[4:])
    else:  # python -m hdrqn_ros.nodes.MODULE
        use.module = argv[2].rsplit(".", 1)[-1]
        use.executable, rest = executable_of_module(use.module), list(argv[3:])
        if use.executable is None:
            use.problems.append(f"hdrqn_ros.nodes.{use.module} is the module of no node executable")
    ros_args = rest.index("--ros-args") if "--ros-args" in rest else len(rest)
    use.own_args = rest[:ros_args]
    tail = rest[ros_args + 1:]
    use.parameters = [tail[i + 1].split(":=")[0] for i, word in enumerate(tail[:-1]) if word == "-p"]
    return use


def declared_launch_arguments(path: Path) -> set[str]:
    """The names of a launch file's ``DeclareLaunchArgument("name", ...)`` calls."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    return {ast.literal_eval(call.args[0]) for call in ast.walk(tree)
            if isinstance(call, ast.Call) and getattr(call.func, "id", None) == "DeclareLaunchArgument"}


@functools.cache
def managed_flag() -> str:
    """``hdrqn_ros.nodes.process.MANAGED_FLAG``, read from its source (importing it needs rclpy):
    the one argument a node executable takes before ``--ros-args``."""
    source = (ROOT / "hdrqn_ros" / "nodes" / "process.py").read_text(encoding="utf-8")
    return re.search(r'^MANAGED_FLAG = "([^"]+)"', source, re.M).group(1)


def has_main_block(path: Path) -> bool:
    source = path.read_text(encoding="utf-8")
    return re.search(r"^if __name__ == [\"']__main__[\"']:", source, re.M) is not None


def ros_static_problems(command: Command) -> list[str]:
    """Executable, launch file, launch arguments, own arguments and ``python -m`` module."""
    use = ros_use(command.argv)
    problems = list(use.problems)
    if use.launch_file is not None:
        path = ROOT / "launch" / use.launch_file
        if not path.is_file():
            return [f"launch/{use.launch_file} does not exist"]
        declared = declared_launch_arguments(path)
        problems += [f"{use.launch_file} declares no launch argument {name!r} (it declares {sorted(declared)})"
                     for name in use.launch_args if name not in declared]
        return problems
    if use.executable is not None:
        if use.executable not in NODES or use.executable not in console_scripts():
            problems.append(f"no node executable {use.executable!r} (setup.py's are {sorted(console_scripts())})")
        problems += [f"{use.executable} takes no argument {word!r} before --ros-args (only {managed_flag()})"
                     for word in use.own_args if word != managed_flag()]
    if use.module is not None and not has_main_block(ROOT / "hdrqn_ros" / "nodes" / f"{use.module}.py"):
        problems.append(f"python -m hdrqn_ros.nodes.{use.module} starts nothing: the module has no __main__ block")
    return problems


def node_parameter_names(executable: str) -> set[str]:
    """The parameters ``executable`` declares (its ``PARAMETERS``) and rclpy's ``use_sim_time``."""
    from hdrqn_ros.nodes.parameter_tables import node_parameters

    return set(node_parameters()[executable][1]) | {"use_sim_time"}


def ros_parameter_problems(command: Command) -> list[str]:
    use = ros_use(command.argv)
    if use.executable not in NODES:
        return []  # reported by the static check
    declared = node_parameter_names(use.executable)
    return [f"{use.executable} declares no parameter {name!r}" for name in use.parameters if name not in declared]


ROS_COMMANDS = commands_of("ros")
WITH_PARAMETERS = [c for c in ROS_COMMANDS if ros_use(c.argv).parameters]


@pytest.mark.parametrize("command", ROS_COMMANDS, ids=ids(ROS_COMMANDS))
def test_ros_command_names_what_exists(command):
    problems = ros_static_problems(command)
    assert not problems, f"{command}: {'; '.join(problems)}"


@NEEDS_RCLPY
@pytest.mark.parametrize("command", WITH_PARAMETERS, ids=ids(WITH_PARAMETERS))
def test_ros_command_parameters_are_declared(command):
    problems = ros_parameter_problems(command)
    assert not problems, f"{command}: {'; '.join(problems)}"


# -- python -m of the package's other modules ---------------------------------------------------
def module_problems(command: Command) -> list[str]:
    """``python -m MODULE`` runs something: the module exists and has a ``__main__`` block
    (a package: a ``__main__.py``)."""
    name = command.argv[2]
    spec = importlib.util.find_spec(name)
    if spec is None or spec.origin is None:
        return [f"no module {name}"]
    origin = Path(spec.origin)
    if origin.name == "__init__.py":
        return [] if (origin.parent / "__main__.py").is_file() else [f"package {name} has no __main__.py"]
    return [] if has_main_block(origin) else [f"python -m {name} runs nothing: the module has no __main__ block"]


MODULE_COMMANDS = commands_of("module")


@pytest.mark.parametrize("command", MODULE_COMMANDS, ids=ids(MODULE_COMMANDS))
def test_python_module_command_runs_something(command):
    problems = module_problems(command)
    assert not problems, f"{command}: {'; '.join(problems)}"


# -- the repository's scripts -------------------------------------------------------------------
def script_problems(command: Command) -> list[str]:
    """The script exists and its source names each ``--flag`` the command gives it."""
    argv = list(command.argv)
    if argv[0] in ("python", "python3"):
        argv = argv[1:]
    path = ROOT / argv[0].removeprefix("./")
    if not path.is_file():
        return [f"{argv[0]} does not exist"]
    source = path.read_text(encoding="utf-8")
    return [f"{argv[0]} has no flag {word}" for word in argv[1:]
            if word.startswith("--") and f'"{word.split("=")[0]}"' not in source]


SCRIPT_COMMANDS = commands_of("script")


@pytest.mark.parametrize("command", SCRIPT_COMMANDS, ids=ids(SCRIPT_COMMANDS))
def test_script_command_names_its_flags(command):
    problems = script_problems(command)
    assert not problems, f"{command}: {'; '.join(problems)}"


# -- every command is checked or known ----------------------------------------------------------
def test_every_command_is_checked():
    unknown = [str(c) for c in all_commands() if kind(c) == "unknown" and (c.doc, c.text) not in SKIPS]
    assert not unknown, ("commands of programs this test neither checks nor knows (check them, or add the "
                         "program to OTHER_PROGRAMS):\n" + "\n".join(unknown))


def test_every_skip_is_still_in_the_docs():
    texts = {(c.doc, c.text) for c in all_commands()}
    stale = [key for key in SKIPS if key not in texts]
    assert not stale, f"SKIPS names commands the docs no longer have: {stale}"


# -- paths --------------------------------------------------------------------------------------
def looks_like_repo_path(word: str) -> bool:
    if word == "README.md":
        return True
    first, slash, rest = word.partition("/")
    return bool(slash) and first in TOP_FOLDERS


def has_placeholder(path: str) -> bool:
    return bool(re.search(r"[<>{}*$…]|\.\.\.", path)) or any(is_placeholder(part) for part in path.split("/"))


SUBPACKAGES = tuple(sorted(p.parent.name for p in (ROOT / "hdrqn_ros").glob("*/__init__.py")))
"""``agents/replay.py`` in the prose is ``hdrqn_ros/agents/replay.py``."""


def path_candidates(token: str) -> list[str]:
    """The repository paths a backticked token names (its words, without a trailing ``:``/``,``
    or a ``:LINE``), made repository-relative (``test_x.py::name`` is under test/,
    ``agents/x.py`` under hdrqn_ros/)."""
    found = []
    for word in token.split():
        word = re.sub(r":\d+(-\d+)?$", "", word.rstrip(":,;.)"))
        if re.fullmatch(r"test_\w+\.py(::.+)?", word):
            word = f"test/{word}"
        elif word.split("/")[0] in SUBPACKAGES and "/" in word:
            word = f"hdrqn_ros/{word}"
        if looks_like_repo_path(word) and not has_placeholder(word.partition("::")[0]) and word not in found:
            found.append(word)
    return found


def command_paths(command: Command) -> list[str]:
    """The repository paths a command names: its words and ``name:=value`` values (lists
    split), not its made-up outputs."""
    found = []
    for word in command.argv:
        value = word.split(":=", 1)[-1]
        for part in value.strip("[]").split(","):
            part = part.strip()
            if looks_like_repo_path(part) and not has_placeholder(part) and part.rstrip("/") not in EXAMPLE_OUTPUTS:
                found.append(part)
    return found


def defined_names(path: Path) -> set[str]:
    """The module-level functions and classes of a test file, and ``Class::method``."""
    tree = ast.parse(path.read_text(encoding="utf-8"))
    names = set()
    for node in tree.body:
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef)):
            names.add(node.name)
        if isinstance(node, ast.ClassDef):
            names |= {f"{node.name}::{item.name}" for item in node.body if isinstance(item, ast.FunctionDef)}
    return names


def path_problem(path: str) -> str | None:
    """None when ``path`` (``file.py::test_name`` too) exists in the repository."""
    file, _, test = path.partition("::")
    if not (ROOT / file).exists():
        return f"{file} does not exist"
    if test:
        test = re.sub(r"\[.*\]$", "", test)
        if test not in defined_names(ROOT / file):
            return f"{file} has no test {test}"
    return None


def doc_paths() -> list[tuple[str, int, str]]:
    """(doc, line, path) of every repository path the docs name: backticked in the prose,
    relative links (from the doc's folder, made repository-relative) and in the commands."""
    found = []
    for doc in DOCS:
        text = doc.read_text(encoding="utf-8")
        for number, token in backticked(text):
            found += [(relative(doc), number, p) for p in path_candidates(token)]
        for number, line in prose_lines(text):
            for target in LINK.findall(line):
                target = target.split("#")[0]
                if target and not re.match(r"[a-z]+:", target) and not target.startswith("/"):
                    resolved = (doc.parent / target).resolve()
                    if resolved.is_relative_to(ROOT):
                        found.append((relative(doc), number, relative(resolved) if resolved != ROOT else "."))
    for command in all_commands():
        found += [(command.doc, command.line, p) for p in command_paths(command)]
    return sorted(set(found))


DOC_PATHS = doc_paths()


@pytest.mark.parametrize("doc,line,path", DOC_PATHS, ids=[f"{d}:{n}:{p}" for d, n, p in DOC_PATHS])
def test_named_path_exists(doc, line, path):
    problem = path_problem(path)
    assert problem is None, f"{doc}:{line}: `{path}`: {problem}"


# -- a sample output that the code decides -----------------------------------------------------
def console_output(doc: Path, command: str) -> list[str]:
    """The lines a ``console`` block of ``doc`` shows after ``$ COMMAND``, up to the next ``$``."""
    for lang, block in fenced_blocks(doc.read_text(encoding="utf-8")):
        lines = [line.strip() for _, line in block]
        if lang == "console" and f"$ {command}" in lines:
            rest = lines[lines.index(f"$ {command}") + 1:]
            return rest[:next((i for i, line in enumerate(rest) if line.startswith("$ ")), len(rest))]
    raise AssertionError(f"{relative(doc)} shows no `$ {command}`")


@NEEDS_RCLPY
def test_the_sample_topic_list_is_the_graphs():
    """docs/topics.md's ``ros2 topic list`` after ``ros2 launch hdrqn_ros train.launch.py``: its
    topics table (hdrqn-v2), the lifecycle nodes' ``transition_event`` and rclpy's own, as
    test_ros_tooling finds them on the running graph."""
    import test_ros_tooling as tooling

    expected = {*tooling.documented_topics(), *tooling.RCLPY_TOPICS,
                *(f"/{node}/{tooling.LIFECYCLE_TOPIC[0]}" for node in tooling.MANAGED)}
    shown = console_output(ROOT / "docs" / "topics.md", "ros2 topic list")
    assert shown == sorted(shown), "ros2 topic list prints the names sorted"
    assert set(shown) == expected, f"missing {sorted(expected - set(shown))}, not there {sorted(set(shown) - expected)}"


# -- python code blocks -------------------------------------------------------------------------
def python_block_imports() -> list[tuple[str, int, str, str]]:
    """(doc, line, module, name) of each ``from hdrqn_ros... import name`` of a python code block."""
    found = []
    for doc in DOCS:
        for lang, block in fenced_blocks(doc.read_text(encoding="utf-8")):
            if lang != "python" or not block:
                continue
            tree = ast.parse("\n".join(line for _, line in block))
            for node in ast.walk(tree):
                if isinstance(node, ast.ImportFrom) and (node.module or "").startswith("hdrqn_ros"):
                    found += [(relative(doc), block[0][0] + node.lineno - 1, node.module, alias.name)
                              for alias in node.names]
    return found


PY_IMPORTS = python_block_imports()


@pytest.mark.parametrize("doc,line,module,name", PY_IMPORTS, ids=[f"{d}:{n}:{m}.{a}" for d, n, m, a in PY_IMPORTS])
def test_python_example_imports_exist(doc, line, module, name):
    loaded = importlib.import_module(module)
    assert hasattr(loaded, name), f"{doc}:{line}: {module} has no {name}"


# -- the checks can fail ------------------------------------------------------------------------
SCRATCH_DOC = """\
Some prose naming `config/quickstart.yaml`, `config/no_such.yaml` and `test/test_docs.py::test_no_such`,
then a span over two lines, `hdrqn train
--out x`, and `scripts/no_such`.

```bash
hdrqn train --episodes 5 \\
    --out runs/x --no-such-flag   # a comment
cd ~/w && hdrqn envs; ros2 run hdrqn_ros no_such_node --ros-args -p a:=1
```

```
done: 5 episodes (output, not a command)
hdrqn eval --checkpoint c.pt
```

```console
$ ros2 launch hdrqn_ros train.launch.py no_such_arg:=1 episodes:=3
/output
```
"""


def scratch_commands() -> list[Command]:
    out = []
    for lang, block in fenced_blocks(SCRATCH_DOC):
        out += [Command("scratch.md", n, tuple(words)) for n, words in block_commands(lang, block)]
    return out + prose_commands("scratch.md", SCRATCH_DOC)


def test_extractor_reads_blocks_continuations_comments_and_separators():
    assert [(c.line, c.text) for c in scratch_commands()] == [
        (6, "hdrqn train --episodes 5 --out runs/x --no-such-flag"),
        (8, "cd ~/w"), (8, "hdrqn envs"), (8, "ros2 run hdrqn_ros no_such_node --ros-args -p a:=1"),
        (13, "hdrqn eval --checkpoint c.pt"),
        (17, "ros2 launch hdrqn_ros train.launch.py no_such_arg:=1 episodes:=3"),
        (2, "hdrqn train --out x"),
    ]
    assert [p for _, token in backticked(SCRATCH_DOC) for p in path_candidates(token)] == [
        "config/quickstart.yaml", "config/no_such.yaml", "test/test_docs.py::test_no_such", "scripts/no_such"]
    assert backticked(SCRATCH_DOC)[-2:] == [(2, "hdrqn train --out x"), (3, "scripts/no_such")]


def test_a_missing_flag_or_subcommand_fails():
    train = scratch_commands()[0]
    assert "unrecognized arguments: --no-such-flag" in hdrqn_problems(train)[0]
    assert hdrqn_problems(Command("x.md", 1, ("hdrqn", "train", "--out", "r"))) == []
    assert flag_problems(("hdrqn", "trian")) == ["hdrqn has no subcommand 'trian'"]
    assert flag_problems(("hdrqn", "bag", "play", "B", "[--no-such]")) == ["hdrqn bag play has no flag --no-such"]
    assert flag_problems(("hdrqn", "bag", "play", "BAG_DIR...", "[--rate", "R]")) == []
    assert flag_problems(("hdrqn", "NAME", "--help")) == [
        "NAME: a placeholder where a subcommand of hdrqn goes (fill it, or add the command to SKIPS)"]


def test_a_missing_executable_launch_argument_or_module_fails():
    commands = scratch_commands()
    assert "no node executable 'no_such_node'" in ros_static_problems(commands[3])[0]
    assert ros_static_problems(commands[5]) == [
        "train.launch.py declares no launch argument 'no_such_arg' (it declares "
        f"{sorted(declared_launch_arguments(ROOT / 'launch' / 'train.launch.py'))})"]
    no_main = Command("x.md", 1, ("python", "-m", "hdrqn_ros.nodes.parameters", "--ros-args"))
    assert kind(no_main) == "module"
    assert module_problems(no_main) == ["python -m hdrqn_ros.nodes.parameters runs nothing: the module has no "
                                        "__main__ block"]
    assert module_problems(Command("x.md", 1, ("python", "-m", "hdrqn_ros.no_such"))) == ["no module hdrqn_ros.no_such"]


@NEEDS_RCLPY
def test_an_undeclared_parameter_fails():
    command = Command("x.md", 1, ("ros2", "run", "hdrqn_ros", "critic", "--ros-args", "-p", "no_such:=1",
                                  "-p", "option_timeout:=60.0"))
    assert ros_parameter_problems(command) == ["critic declares no parameter 'no_such'"]
    assert ros_parameter_problems(Command("x.md", 1, ("ros2", "param", "get", "/group1/critic", "no_such"))) \
        == ["critic declares no parameter 'no_such'"]


def test_a_missing_path_test_or_script_flag_fails():
    assert path_problem("config/quickstart.yaml") is None
    assert path_problem("config/no_such.yaml") == "config/no_such.yaml does not exist"
    assert path_problem("test/test_docs.py::test_named_path_exists") is None
    assert path_problem("test/test_docs.py::test_no_such") == "test/test_docs.py has no test test_no_such"
    assert script_problems(Command("x.md", 1, ("scripts/stress", "--runs", "2", "--no-such"))) == \
        ["scripts/stress has no flag --no-such"]


def test_a_failing_run_fails(tmp_path):
    runs = {"bad": FullRun("x.md", "hdrqn eval --checkpoint", {"c.pt": "{tmp}/missing.pt"})}
    commands = scratch_commands()
    assert documented(runs["bad"], [Command("x.md", 1, commands[4].argv)]).argv == commands[4].argv
    argv = filled(commands[4].argv[1:], runs["bad"].fill, tmp_path)
    assert argv == ["eval", "--checkpoint", f"{tmp_path}/missing.pt"]
    assert filled(("eval", "--episodes", "304", "--num-envs", "8"), {}, tmp_path) == \
        ["eval", "--episodes", "2", "--num-envs", "2"]
    code, output = run_hdrqn(argv, tmp_path)
    assert code == 2 and "missing.pt" in output
