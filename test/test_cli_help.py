"""The command line explains itself: every option of every subcommand has help text, and
every subcommand's --help ends with examples that parse."""

import argparse
import shlex

import pytest

from lgs_wfs_ros.cli import parser


def subcommands():
    sub = next(a for a in parser()._actions if isinstance(a, argparse._SubParsersAction))
    return sub.choices


@pytest.mark.parametrize("verb", sorted(subcommands()))
def test_every_option_has_help_and_the_examples_parse(verb):
    p = subcommands()[verb]
    assert p.description
    for action in p._actions:
        if isinstance(action, argparse._HelpAction):
            continue
        assert action.help and action.help.strip(), f"{verb}: {action.dest} has no help"
    assert p.epilog and p.epilog.startswith("examples:")
    examples = [line.split("#")[0].strip() for line in p.epilog.splitlines()[1:]]
    examples = [e for e in examples if e]
    assert examples, verb
    for example in examples:
        words = shlex.split(example)
        assert words[:2] == ["lgs-wfs", verb], example
        args = parser().parse_args(words[1:])       # SystemExit if it does not parse
        assert args.verb == verb


def test_help_prints_the_examples(capsys):
    with pytest.raises(SystemExit):
        parser().parse_args(["demo", "--help"])
    out = capsys.readouterr().out
    assert "examples:" in out and "--full-frames" in out and "lgs-wfs demo --frames" in out


def test_demo_without_rclpy_names_the_ros_extra(tmp_path):
    """``lgs-wfs demo`` in a venv without the ``ros`` extra: exit 2, one line naming it."""
    import subprocess
    import sys
    block = ("import sys\n"
             "class Block:\n"
             "    def find_spec(self, name, path=None, target=None):\n"
             "        if name == 'rclpy' or name.startswith('rclpy.'):\n"
             "            raise ImportError('rclpy blocked')\n"
             "sys.meta_path.insert(0, Block())\n"
             "from lgs_wfs_ros import cli\n"
             f"sys.exit(cli.main(['demo', '--out-dir', {str(tmp_path)!r}]))")
    out = subprocess.run([sys.executable, "-c", block], capture_output=True, text=True, timeout=60)
    assert out.returncode == 2, out.stderr
    assert "Traceback" not in out.stderr and len(out.stderr.strip().splitlines()) == 1
    assert "'ros' extra" in out.stderr
