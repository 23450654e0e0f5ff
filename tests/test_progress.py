"""Progress bars in a log: a bar whose output is a pipe writes a few lines, not one per update."""

import subprocess
import sys

SCRIPT = """
import time
from adadex.progress import progress_bar
for _ in progress_bar(range(400), desc="work"):
    time.sleep(0.002)
"""


def test_a_bar_written_to_a_pipe_does_not_flood_the_log():
    r = subprocess.run([sys.executable, "-c", SCRIPT], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr
    states = [s for s in r.stderr.replace("\r", "\n").split("\n") if "work" in s]
    assert 1 <= len(states) <= 3, states          # the start and the end; plain tqdm wrote ~10 here
    assert "400/400" in states[-1]
