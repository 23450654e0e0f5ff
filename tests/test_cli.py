import json
import subprocess
import sys

from adadex.cli import main
from adadex.sim.robot import JOINT_NAMES, TRACKED_SITES


def test_help_runs():
    out = subprocess.run([sys.executable, "-m", "adadex.cli", "--help"], capture_output=True, text=True)
    assert out.returncode == 0
    assert "sim" in out.stdout and "demo" in out.stdout


def test_sim_info_json(capsys):
    assert main(["sim", "info", "--json"]) == 0
    info = json.loads(capsys.readouterr().out)
    assert info["joint_names"] == list(JOINT_NAMES)
    assert info["tracked_links"] == list(TRACKED_SITES)
    assert info["control_hz"] == 12.0
    assert abs(info["physics_timestep"] * info["substeps"] - 1 / 12) < 1e-12
    assert all(j["range"][0] < j["range"][1] and j["kp"] > 0 for j in info["joints"])
    assert len(info["objects"]) >= 50
    assert sum(o["split"] == "held_out" for o in info["objects"]) == 5
    assert len({o["category"] for o in info["objects"]}) >= 10


def test_sim_info_table(capsys):
    assert main(["sim", "info"]) == 0
    out = capsys.readouterr().out
    assert "arm_j1" in out and "held out" in out
