"""Running recipes as a user does, many in one interpreter, and checking a refusal: shared by the
reliability tests of the training and evaluation recipes."""

from __future__ import annotations

import json
import os
import subprocess
import sys

#: runs each case ``[script, args, watched folder]`` as ``python <script> <args>`` would, one after the
#: other in one interpreter; prints per case [exit code, stderr, the watched folder's files before, after]
_RUN = """
import contextlib, hashlib, io, json, runpy, sys
from pathlib import Path

def tree(folder):
    if folder is None or not Path(folder).exists():
        return None
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(Path(folder).rglob("*")) if p.is_file()}

results = []
for script, args, watched in json.loads(sys.argv[1]):
    before = tree(watched)
    err, code = io.StringIO(), 0
    sys.argv = [script, *args]
    with contextlib.redirect_stderr(err):
        try:
            runpy.run_path(script, run_name="__main__")
        except SystemExit as e:
            code = e.code
    results.append([code, err.getvalue(), before, tree(watched)])
print(json.dumps(results))
"""


def run_recipes(cases: dict, cwd, wandb_mode: str, *, quiet: bool = False) -> dict:
    """``{name: (script, args, watched folder or None)}`` → ``{name: {code, err, before, after}}``;
    ``quiet``: nothing may reach the process's own stderr beside what each case captured."""
    res = subprocess.run([sys.executable, "-c", _RUN, json.dumps(list(cases.values()), default=str)],
                         capture_output=True, text=True, timeout=600, cwd=cwd,
                         env={**os.environ, "OMP_NUM_THREADS": "1", "WANDB_MODE": wandb_mode})
    assert res.returncode == 0 and not (quiet and res.stderr), res.stderr[-3000:]
    out = dict(zip(cases, json.loads(res.stdout.splitlines()[-1])))
    return {k: {"code": v[0], "err": v[1], "before": v[2], "after": v[3]} for k, v in out.items()}


def refused(r: dict, *fragments: str, existed: bool = False) -> str:
    """One line on stderr holding every fragment, exit code 2, the watched folder byte for byte unchanged
    (``existed``: and it was there before)."""
    lines = [line for line in r["err"].splitlines() if line.strip()]
    assert r["code"] == 2 and len(lines) == 1 and "Traceback" not in r["err"], r["err"][-2000:]
    for f in fragments:
        assert f in lines[0], (f, lines[0])
    assert r["before"] == r["after"], "the refusal wrote into the folder"
    assert r["before"] is not None or not existed, "the watched folder was not there"
    return lines[0]
