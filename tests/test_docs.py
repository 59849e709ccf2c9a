"""The repository's documents: no absolute machine paths, links that resolve, every driver they name
present, a README a newcomer reads in minutes with its picture."""

import re
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
TEXT = (".md", ".py", ".toml", ".json", ".txt", ".cfg", ".yml", ".yaml", ".sh", ".c")
#: An absolute path of one machine: a home, a scratch or work folder, a Windows drive.
MACHINE_PATH = re.compile(r"(?<![\w.~$/:-])/(?:work|root|home|tmp|Users|mnt|scratch)/|\b[A-Za-z]:\\\\?[A-Za-z]")
#: Where such a string is right: (file, the text matched). System paths (/dev/null, /usr/bin/env), URLs
#: and ~ or $HOME paths are not matched at all.
ALLOWED: set[tuple[str, str]] = set()
LINK = re.compile(r"\[[^\]]*\]\(([^)\s]+)\)")


def tracked(*suffixes) -> list[Path]:
    try:
        names = subprocess.run(["git", "ls-files", "-z"], cwd=ROOT, capture_output=True, check=True,
                               timeout=60).stdout.decode().split("\0")
    except (OSError, subprocess.CalledProcessError):
        pytest.skip("not a git checkout")
    return [ROOT / n for n in names if n and (n.endswith(suffixes) or Path(n).name == "Makefile")
            and (ROOT / n).is_file()]


def test_no_document_or_source_names_an_absolute_machine_path():
    found = []
    for path in tracked(*TEXT):
        rel = path.relative_to(ROOT).as_posix()
        for no, line in enumerate(path.read_text(encoding="utf-8", errors="replace").splitlines(), 1):
            for m in MACHINE_PATH.finditer(line):
                if (rel, m.group(0)) not in ALLOWED:
                    found.append(f"{rel}:{no}: {line.strip()[:140]}")
    assert not found, "absolute machine paths (use a path in the repository or a command):\n" + "\n".join(found)


def test_the_check_finds_machine_paths_and_spares_urls_and_system_files():
    bad = [f"made by {q}/{root}/runs33/driver.py" for q in ("", "`") for root in ("work", "tmp", "root", "home")]
    bad.append("C:" + "\\Users\\me")
    good = ["https://example.org/home/page", "#!/usr/bin/env python3", "> /dev/null", "~/.cache/gvae/kernels",
            "$HOME/work/x", "a/tmp/b", "%LOCALAPPDATA%\\gvae\\kernels"]
    assert all(MACHINE_PATH.search(s) for s in bad)
    assert not any(MACHINE_PATH.search(s) for s in good)


def _slug(heading: str) -> str:
    text = heading.strip().lower().replace("`", "")
    return re.sub(r"[^\w\- ]", "", text).replace(" ", "-")


def _anchors(path: Path) -> set[str]:
    fence, out = False, set()
    for line in path.read_text(encoding="utf-8").splitlines():
        fence ^= line.startswith("```")
        m = None if fence else re.match(r"^#+ (.*)$", line)
        if m:
            out.add(_slug(m.group(1)))
    return out


def test_relative_links_in_the_documents_resolve():
    broken = []
    for doc in tracked(".md"):
        for target in LINK.findall(doc.read_text(encoding="utf-8")):
            if re.match(r"^[a-z]+:", target):
                continue
            name, _, anchor = target.partition("#")
            dest = (doc.parent / name).resolve() if name else doc
            if not dest.exists() or (anchor and dest.suffix == ".md" and anchor not in _anchors(dest)):
                broken.append(f"{doc.relative_to(ROOT)}: {target}")
    assert not broken, "links that lead nowhere:\n" + "\n".join(broken)


def test_every_driver_the_documents_name_is_in_the_repository():
    """A figure's command names a tools/ script or a benchmark module: each must exist."""
    missing = []
    for doc in tracked(".md"):
        text = doc.read_text(encoding="utf-8")
        for script in set(re.findall(r"\btools/[\w/]+\.py\b", text)):
            if not (ROOT / script).is_file():
                missing.append(f"{doc.relative_to(ROOT)}: {script}")
        for module in set(re.findall(r"-m (gvae_core(?:\.\w+)+)", text)):
            base = ROOT / module.replace(".", "/")
            if not (base.with_suffix(".py").is_file() or (base / "__init__.py").is_file()):
                missing.append(f"{doc.relative_to(ROOT)}: {module}")
        for name in set(re.findall(r"-m gvae_core\.benchmarks (\w+)", text)):
            if not (ROOT / "gvae_core" / "benchmarks" / f"{name}.py").is_file():
                missing.append(f"{doc.relative_to(ROOT)}: benchmarks {name}")
    assert not missing, "\n".join(missing)


def test_the_readme_is_short_and_shows_the_demo_picture():
    readme = (ROOT / "README.md").read_text(encoding="utf-8")
    assert len(readme.splitlines()) < 250
    pictures = re.findall(r"!\[[^\]]*\]\(([^)]+)\)", readme)
    assert "docs/demo.png" in pictures
    assert (ROOT / "docs" / "demo.png").stat().st_size < 150_000
