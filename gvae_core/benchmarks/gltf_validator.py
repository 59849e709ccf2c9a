"""Khronos's glTF validator (npm `gltf-validator`, the official validator compiled to JavaScript),
installed once into the npm cache folder (`npm.installed`, about 0.5 MB) and run with node.

`validate(path)` returns its report (a dict: `issues.messages`, each with code, severity 0 error,
1 warning, 2 info, 3 hint, and a JSON pointer); a .gltf's external buffers are loaded and checked
too. tests/test_splat_transform.py holds the project's .glb and splat-transform's to it.
"""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

from .npm import Unavailable, cache_root, installed, node

__all__ = ["VERSION", "PACKAGE", "Unavailable", "validate"]

VERSION = "2.0.0-dev.3.10"
PACKAGE = f"gltf-validator@{VERSION}"
_MODULE = Path("node_modules", "gltf-validator")
# Reads the file named by argv[1], loads external resources beside it, prints the report as JSON.
_SCRIPT = """
const fs = require('fs'), path = require('path');
const validator = require(process.argv[1]);
const file = path.resolve(process.argv[2]);
validator.validateBytes(new Uint8Array(fs.readFileSync(file)), {
    uri: path.basename(file), maxIssues: 0, writeTimestamp: false,
    externalResourceFunction: (uri) => new Promise((resolve, reject) =>
        fs.readFile(path.resolve(path.dirname(file), decodeURIComponent(uri)),
                    (err, data) => err ? reject(err.toString()) : resolve(new Uint8Array(data))))
}).then((report) => process.stdout.write(JSON.stringify(report)),
        (error) => { process.stderr.write(String(error)); process.exit(1); });
"""


def module(*, install: bool = True) -> Path:
    """The installed gltf-validator module folder (installing it first when missing and `install`)."""
    return installed(PACKAGE, cache_root() / f"gltf-validator-{VERSION}", _MODULE, install=install) / _MODULE


def validate(path, *, install: bool = True, timeout: float = 120) -> dict:
    """The validator's report on the glTF file at `path`; RuntimeError when it cannot run."""
    proc = subprocess.run([node(), "-e", _SCRIPT, str(module(install=install)), str(path)],
                          capture_output=True, text=True, timeout=timeout)
    if proc.returncode != 0:
        raise RuntimeError(f"gltf-validator on {path} failed:\n{proc.stdout}{proc.stderr}")
    return json.loads(proc.stdout)
