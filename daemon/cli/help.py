"""``--help`` that reads like a terminal page (issue 31 item 4).

Each subcommand's module docstring is its manual, written for the source (Sphinx
roles, double backquotes, paragraphs wrapped at 88 columns). On a terminal,
:func:`tidy` makes every parser lead with its usage, a one-line summary and its
options, and puts the docstring after them as plain text (:func:`plain_text`),
re-filled to the terminal's width without breaking a word (:class:`HelpFormatter`;
argparse's own breaks a word longer than the column, e.g. a comma-joined list).
"""

from __future__ import annotations

import argparse
import re
import textwrap

#: Sphinx cross-reference roles (``:func:`x```, ``:func:`~a.b```: the last part).
_ROLE = re.compile(
    r":(?:func|meth|class|mod|data|attr|obj|exc|ref|doc|const):`(~?)([^`]+)`"
)
#: A hyperlink, ```text <url>`_``: text (url).
_LINK = re.compile(r"`([^`<]+?)\s*<([^>]+)>`_{1,2}")
#: A bullet or numbered item that starts a line.
_ITEM = re.compile(r"^\s*(?:[-*•]|\d+[.)])\s+")


def _role(m: re.Match[str]) -> str:
    name = m.group(2)
    return name.rsplit(".", 1)[-1] if m.group(1) else name


def plain_text(doc: str) -> str:
    """A docstring as plain text: roles, links and literal quotes dropped (their text
    kept), a literal block's ``::`` made ``:``; paragraphs and indentation kept."""
    text = textwrap.dedent(doc).strip("\n")
    text = _ROLE.sub(_role, text)
    text = _LINK.sub(r"\1 (\2)", text)
    text = text.replace("``", "")
    text = re.sub(r"(?<![`\w])`([^`\n]+)`(?!`)", r"\1", text)  # default role
    return re.sub(r"(?<=\S)::$", ":", text, flags=re.MULTILINE)


def _fill(text: str, width: int, indent: str = "", hang: str = "") -> str:
    return textwrap.fill(
        text, width, initial_indent=indent, subsequent_indent=indent + hang,
        break_long_words=False, break_on_hyphens=False,
    )  # fmt: skip


class HelpFormatter(argparse.HelpFormatter):
    """Option help wrapped at the width without breaking a word; the description and
    epilog re-filled paragraph by paragraph (a bullet each on its own, hanging; a
    paragraph all indented, e.g. a command line, kept as it is)."""

    def _split_lines(self, text: str, width: int) -> list[str]:
        text = self._whitespace_matcher.sub(" ", text).strip()
        return textwrap.wrap(
            text, width, break_long_words=False, break_on_hyphens=False
        ) or [""]

    def _fill_text(self, text: str, width: int, indent: str) -> str:
        out = []
        for para in re.split(r"\n[ \t]*\n", text.strip("\n")):
            lines = para.splitlines()
            if all(line[:1] in (" ", "\t") for line in lines):
                out.append("\n".join(indent + line for line in lines))
                continue
            items: list[list[str]] = []
            for line in lines:
                if _ITEM.match(line) or not items:
                    items.append([line.strip()])
                else:
                    items[-1].append(line.strip())
            filled = []
            for item in items:
                joined = " ".join(item)
                m = _ITEM.match(joined)
                hang = " " * len(m.group(0).strip() + " ") if m else ""
                filled.append(_fill(joined, width, indent, hang))
            out.append("\n".join(filled))
        return "\n\n".join(out)


def _subparsers(parser: argparse.ArgumentParser) -> list[argparse._SubParsersAction]:
    return [a for a in parser._actions if isinstance(a, argparse._SubParsersAction)]


def tidy(
    parser: argparse.ArgumentParser,
    summary: str = "",
    _seen: set[int] | None = None,
) -> None:
    """Make ``parser`` and every subparser below it lead with usage, a one-line
    summary (``summary``: the help its parent lists it with) and options, with the
    docstring (its ``description``) after them as plain text."""
    seen = set() if _seen is None else _seen
    if id(parser) in seen:  # an alias of a parser already done
        return
    seen.add(id(parser))
    doc = parser.description
    if _seen is None:  # the top-level parser: its description is a summary already
        parser.description = plain_text(doc) if doc else None
    else:
        parser.description = summary[:1].upper() + summary[1:] if summary else None
        if parser.description and not parser.description.endswith("."):
            parser.description += "."
        parser.epilog = plain_text(doc) if doc else None
    parser.formatter_class = HelpFormatter
    for action in _subparsers(parser):
        helps = {a.dest: a.help or "" for a in action._choices_actions}
        for name, sub in action.choices.items():
            tidy(sub, helps.get(name, ""), seen)
