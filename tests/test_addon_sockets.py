"""gvae_addon wires node sockets by name and type (`gvae_addon.nodes.socket`), never by position: a
node's sockets are laid out differently from one Blender version to the next (Random Value's
outputs in 5.2 broke every import wired by position)."""

import re
from pathlib import Path

ADDON = Path(__file__).resolve().parents[1] / "gvae_addon"
#: `inputs[0]`, `outputs[-1]`, and walking a node's sockets in order (zip / list / enumerate).
POSITIONAL = re.compile(r"\b(inputs|outputs)\s*\[\s*-?\d|\b(zip|list|enumerate)\([^)]*\.(inputs|outputs)\b")


def test_the_pattern_finds_wiring_by_position():
    for line in ("b.link(rand.outputs[1], keep_frac.inputs[0])", "for s, v in zip(n.inputs, (a, b)):",
                 "return list(n.outputs)", "x = node.inputs[ -1 ]"):
        assert POSITIONAL.search(line), line
    for line in ('inp(n, "Value", "VALUE", 1)', "for s in (node.outputs if output else node.inputs)"):
        assert not POSITIONAL.search(line), line


def test_no_socket_by_position_in_the_addon():
    hits = [f"{path.name}:{i}: {line.strip()}" for path in sorted(ADDON.glob("*.py"))
            for i, line in enumerate(path.read_text().splitlines(), 1) if POSITIONAL.search(line)]
    assert not hits, "\n".join(hits)
