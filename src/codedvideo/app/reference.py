"""The command-line reference, generated: every command's options (from the parser, in its groups, with the
defaults it holds) and every pipeline.yaml key (from the config's schema, with the built-in file's default and
comment).  ``python -m codedvideo.app.reference > docs/reference.md`` writes it (``make docs`` does), so the
reference cannot drift from the code; a test compares the two.
"""

from __future__ import annotations

import argparse
import re
import sys

from pydantic import BaseModel

from codedvideo.api.config import DEFAULT_CACHE, PipelineConfig, default_config_path

#: A key line of pipeline.yaml (set or commented out) with its trailing comment.
_KEY = re.compile(r"^(?P<indent> *)(?:# )?(?P<key>[a-z][a-z0-9_]*):(?P<value>[^#]*)(?:#\s?(?P<comment>.*))?$")
#: A comment that continues the line above (a comment alone, aligned under the first).
_MORE = re.compile(r"^ {10,}#\s?(?P<comment>.*)$")


def _cell(text: str) -> str:
    return " ".join(str(text).split()).replace("|", "\\|")


def _subcommands(parser: argparse.ArgumentParser) -> dict[str, argparse.ArgumentParser]:
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            return dict(action.choices)
    return {}


def _option_rows(parser: argparse.ArgumentParser) -> list[str]:
    """The options of one parser as markdown, a table a group."""
    formatter = parser._get_formatter()
    out = []
    for group in parser._action_groups:
        actions = [a for a in group._group_actions if a.dest != "help"]
        if not actions or all(isinstance(a, argparse._SubParsersAction) for a in actions):
            continue
        out += ["", f"*{group.title}*" + (f": {group.description}" if group.description else ""), "",
                "| option | value | what it does |", "|---|---|---|"]
        for a in actions:
            name = ", ".join(f"`{s}`" for s in a.option_strings) or f"`{a.metavar or a.dest}`"
            value = "" if a.nargs == 0 else (f"one of {', '.join(map(str, a.choices))}" if a.choices
                                              else (a.metavar if isinstance(a.metavar, str) else a.dest.upper()))
            help_text = (formatter._get_help_string(a) or "") % dict(default=a.default)
            out.append(f"| {name} | {_cell(value)} | {_cell(help_text)} |")
    return out


def commands_reference(parser: argparse.ArgumentParser, prefix: str = "codedvideo") -> list[str]:
    """Every command and its options, nested commands included."""
    out = []
    for name, sub in _subcommands(parser).items():
        nested = _subcommands(sub)
        if nested:
            out += commands_reference(sub, f"{prefix} {name}")
            continue
        out += ["", f"### `{prefix} {name}`", "", _cell(sub.description or _help_of(parser, name))]
        out += _option_rows(sub)
    return out


def _help_of(parser: argparse.ArgumentParser, name: str) -> str:
    for action in parser._actions:
        if isinstance(action, argparse._SubParsersAction):
            for choice in action._choices_actions:
                if choice.dest == name:
                    return choice.help or ""
    return ""


def _comments(text: str) -> dict[str, tuple[str, str]]:
    """pipeline.yaml's keys, dotted (``report.dictionary.atoms``) -> (value as written, comment)."""
    found: dict[str, tuple[str, str]] = {}
    sections: list[tuple[int, str]] = []  # (indent, key) of the sections the line is in
    last = None
    for line in text.splitlines():
        more = _MORE.match(line)
        if more and last is not None:
            value, comment = found[last]
            found[last] = (value, f"{comment} {more['comment']}".strip())
            continue
        m = _KEY.match(line)
        if not m:
            last = None
            continue
        indent = len(m["indent"])
        sections = [s for s in sections if s[0] < indent]
        dotted = ".".join([k for _, k in sections] + [m["key"]])
        found[dotted] = (m["value"].strip(), (m["comment"] or "").strip())
        if not m["value"].strip():
            sections.append((indent, m["key"]))
        last = dotted
    return found


def config_keys(model: type[BaseModel] = PipelineConfig, prefix: str = "") -> list[str]:
    """Every key of pipeline.yaml, dotted, in the schema's order (a section's keys after it)."""
    keys = []
    for name, field in model.model_fields.items():
        kind = field.annotation
        if isinstance(kind, type) and issubclass(kind, BaseModel):
            keys += config_keys(kind, f"{prefix}{name}.")
        else:
            keys.append(prefix + name)
    return keys


def _default_of(dotted: str):
    value = PipelineConfig()
    for part in dotted.split("."):
        value = getattr(value, part)
    return value


def config_reference() -> list[str]:
    """Every pipeline.yaml key: its default and what it does (the built-in file's comment)."""
    written = _comments(default_config_path().read_text(encoding="utf-8"))
    out = ["", "| key | default | what it does |", "|---|---|---|"]
    for key in config_keys():
        value, comment = written.get(key, ("", ""))
        default = value or repr(_default_of(key))
        out.append(f"| `{key}` | `{_cell(default)}` | {_cell(comment)} |")
    return out


def reference() -> str:
    """The whole reference page, markdown."""
    from codedvideo.app.cli import _parser

    parser = _parser()
    head = ["# Command-line and pipeline.yaml reference", "",
            "Generated from the command line's parser and pipeline.yaml's schema (`make docs`); the guide to the "
            "commands is [Command line](cli.md).  `codedvideo COMMAND --help` prints the same options.", "",
            "## Commands"]
    tail = ["", "## pipeline.yaml keys", "",
            "`codedvideo run` and `codedvideo report` read these; `codedvideo config` prints the built-in file with "
            "every key at its default.  Unknown keys are errors."]
    text = "\n".join(head + commands_reference(parser) + tail + config_reference()) + "\n"
    return text.replace(DEFAULT_CACHE, "the user's cache folder")  # (the same page on every machine)


if __name__ == "__main__":
    sys.stdout.write(reference())
