"""A marked block of a markdown file (``<!-- NAME:begin -->`` ... ``<!-- NAME:end -->``) replaced by a generated
table: how `cdrb report --docs` and `cdrb select --docs` keep a results page current without touching its prose."""

from __future__ import annotations

import re
from pathlib import Path

from cdrb_cli import ui
from cdrb_cli.errors import BadInput
from cdrb_cli.settings import clip

#: a block name: letters, digits, ``.``, ``_`` and ``-``, starting with a letter or digit, no ``--`` (which would
#: end or break the HTML comment of its markers)
BLOCK_NAME = re.compile(r"[A-Za-z0-9](?:[A-Za-z0-9._]|-(?!-)){0,63}")


#: any block's begin or end marker
MARKER = re.compile(r"<!-- [A-Za-z0-9][A-Za-z0-9._-]{0,63}:(?:begin|end) -->")


def check_block_name(name: str) -> None:
    """Refuse a ``--block`` name that cannot be put in a marker line: empty, blank, or with a character outside
    :data:`BLOCK_NAME` (a space, ``>``, ``--``, a line break would break the markers or match other text)."""
    if not BLOCK_NAME.fullmatch(name):
        raise BadInput(
            f"--block {clip(name, 80)!r}: not a block name (letters, digits, '.', '_' and '-', at most 64, starting "
            "with a letter or digit, no '--')",
            hint="e.g. --block table1-mazes, the NAME of the <!-- NAME:begin --> marker",
        )


def newline_of(text: str) -> str:
    """The line ending a text mostly uses: CRLF when more of its lines end so than with a bare LF."""
    crlf = text.count("\r\n")
    return "\r\n" if crlf > text.count("\n") - crlf else "\n"


def replace_block(text: str, name: str, block: str, where: str) -> str:
    """``text`` with the part between ``<!-- NAME:begin -->`` and ``<!-- NAME:end -->`` replaced by ``block``, whose
    lines end as ``text``'s mostly do (a CRLF file stays CRLF); the text around the block is kept as it is."""
    check_block_name(name)
    begin, end = f"<!-- {name}:begin -->", f"<!-- {name}:end -->"
    pattern = re.compile(re.escape(begin) + ".*?" + re.escape(end), re.S)
    if not pattern.search(text):
        raise BadInput(
            f"--docs {where}: no {begin} ... {end} block", hint="add the two marker lines where the table goes"
        )
    if text.count(begin) != 1 or text.count(end) != 1:
        raise BadInput(
            f"--docs {where}: {begin} appears {text.count(begin)} times and {end} {text.count(end)}: which block "
            "to replace is ambiguous",
            hint="keep one pair of markers per block name (give the others their own --block names)",
        )
    if begin in block or end in block:
        raise BadInput(f"--docs {where}: the report itself holds a {name} marker", hint="check the evals' names")
    found = pattern.search(text)
    inner = MARKER.search(text, found.start() + len(begin), found.end() - len(end))
    if inner is not None:  # replacing this block would delete the other's marker, and break it
        raise BadInput(
            f"--docs {where}: the {name} block holds another block's marker ({inner.group(0)}): blocks nest or overlap",
            hint="keep each block's markers outside every other block",
        )
    nl = newline_of(text)  # the new lines end as the file's mostly do; the text around the block is kept byte for byte
    new = f"{begin}\n{block.rstrip()}\n{end}".replace("\r\n", "\n").replace("\n", nl)
    return text[: found.start()] + new + text[found.end() :]


def check_docs_block(docs: Path, block: str, text: str, inputs) -> None:
    """Refuse, before anything is written, a ``--docs`` FILE that is missing, not a file, one of ``inputs``,
    read-only, or without exactly one pair of ``block`` markers."""
    import stat

    from cdrb_cli.artifacts import check_output
    from cdrb_cli.artifacts.core import read_input_text

    if not docs.is_file():
        why = "no such file" if not docs.exists() else "not a regular file (a folder, device or FIFO)"
        raise BadInput(f"--docs {docs}: {why}", hint="name an existing markdown file with the marked block")
    check_output(docs, True, "--docs", inputs)  # rewritten in place, never one of the inputs
    if not docs.stat().st_mode & stat.S_IWUSR:
        raise BadInput(f"--docs {docs}: is read-only", hint=f"make it writable (chmod u+w {docs}) first")
    replace_block(read_input_text(docs, "--docs", 1 << 24, "markdown file", "name the markdown file"),
                  block, text, str(docs))  # fmt: skip


def write_docs_block(docs: Path, block: str, text: str, inputs) -> None:
    """Replace ``block`` of the markdown file ``docs`` by ``text``: an output like ``--out`` (never one of
    ``inputs``, locked, written atomically), rewritten in place by design, keeping the file's permissions."""
    import stat

    from cdrb_cli.artifacts import atomic_path, claim_output
    from cdrb_cli.artifacts.core import read_input_text

    try:
        with claim_output(docs, True, "--docs", inputs), atomic_path(docs) as tmp:
            old = read_input_text(docs, "--docs", 1 << 24, "markdown file", "name the markdown file")
            tmp.write_text(replace_block(old, block, text, str(docs)), encoding="utf-8", newline="")
            tmp.chmod(stat.S_IMODE(docs.stat().st_mode))  # the file keeps who may read it
    except PermissionError as exc:  # an immutable file, a folder that refuses the rename
        raise BadInput(f"--docs {docs}: cannot be replaced ({exc.strerror})",
                       hint="check the file's and its folder's permissions and attributes") from None  # fmt: skip
    ui.log(f"block {block} of {docs} rewritten")
