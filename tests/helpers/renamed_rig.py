"""A shipped rig rewritten with every marker renamed to a name no take uses (the
take's labels kept as its aliases): the rig a lab writes from RIGS.md for its own
names (issue 28 item 5). Used by ``test_marker_names`` and ``test_live_marker_names``.
"""

from __future__ import annotations

import json
import re
from collections.abc import Callable
from importlib import resources
from pathlib import Path

from retargetd.daemon.body.rig import Rig, load_rig

#: The prefix every renamed rig marker gets: no take label starts with it.
NEW = "zq_"


def write_renamed_rig(
    name: str, path: Path, extra_alias: Callable[[str], str] | None = None
) -> tuple[Rig, dict[str, str]]:
    """The shipped rig ``name`` rewritten with every marker ``M`` named ``zq_M``:
    its ``[markers]`` entry keeps the original labels as aliases (plus
    ``extra_alias(first label)`` when given), and every other mention of a marker in
    the file (segments, points, rules, bones, lateral, ``[fit.markers.M]``) is
    renamed with it. Checked by parsing the file back.

    Returns:
        The rig loaded from ``path`` and old name -> new name.
    """
    original = load_rig(name)
    text = (resources.files("retargetd.daemon.body.rigs") / f"{name}.toml").read_text()
    new_of = {m: NEW + m for m in original.markers}
    names = sorted(new_of, key=len, reverse=True)
    token = re.compile(r"(?<![\w:])(" + "|".join(map(re.escape, names)) + r")(?![\w:])")
    entry = re.compile(r"^\s*([A-Za-z_]\w*)\s*=")
    section = ""
    lines = []
    for line in text.splitlines():
        head = re.match(r"^\s*\[\[?\s*([^\]]+?)\s*\]", line)
        if head:
            section = head.group(1)
        found = entry.match(line) if section == "markers" and not head else None
        if found and found.group(1) in new_of:
            old = found.group(1)
            aliases = list(original.markers[old])
            if extra_alias is not None:
                aliases.append(extra_alias(aliases[0]))
            lines.append(f"{new_of[old]} = {json.dumps(aliases)}")
        elif section == "markers" and not head:
            lines.append(line)
        else:
            lines.append(token.sub(lambda m: new_of[m.group(1)], line))
    path.write_text("\n".join(lines) + "\n")
    rig = load_rig(path)
    # The rewrite is a pure rename: same markers in the same order, same labels.
    assert rig.marker_names == tuple(new_of.values())
    for old, new in new_of.items():
        want = original.markers[old]
        if extra_alias is not None:
            want = (*want, extra_alias(want[0]))
        assert rig.markers[new] == want
    assert len(rig.points) == len(original.points)
    assert rig.bone_names == original.bone_names
    assert set(rig.fit.markers) == {new_of[m] for m in original.fit.markers}
    return rig, new_of
