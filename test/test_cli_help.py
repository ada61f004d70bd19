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
