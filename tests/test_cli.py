import json
import subprocess
import sys

from adadex.cli import main
from adadex.sim.robot import JOINT_NAMES, TRACKED_SITES


def test_help_runs():
    out = subprocess.run([sys.executable, "-m", "adadex.cli", "--help"], capture_output=True, text=True)
    assert out.returncode == 0
    assert "sim" in out.stdout and "demo" in out.stdout


HEAVY = ("torch", "torchrl", "tensordict", "mujoco")


def _modules_after_main(argv: list[str]) -> tuple[int, str, list[str]]:
    """Run ``adadex.cli.main(argv)`` in a fresh interpreter: its exit code, stdout and which of
    :data:`HEAVY` it imported."""
    code = ("import sys, json\nfrom adadex.cli import main\n"
            f"try:\n    rc = main({argv!r})\nexcept SystemExit as e:\n    rc = e.code\n"
            f"print(json.dumps([rc, [m for m in {HEAVY!r} if m in sys.modules]]))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    rc, loaded = json.loads(out.stdout.strip().splitlines()[-1])
    return rc, out.stdout, loaded


def test_help_imports_no_torch_nor_mujoco():
    """``adadex --help`` is quick: the parser is built without torch, TorchRL or MuJoCo (the subcommands
    defined elsewhere get their arguments only when used; issue 45)."""
    rc, out, loaded = _modules_after_main(["--help"])
    assert rc == 0 and "encoder" in out and "sysid" in out
    assert loaded == []


def test_subcommand_help_is_complete():
    """A lazily filled subcommand shows its full help, and its subcommands' (and parses them)."""
    rc, out, loaded = _modules_after_main(["data", "build", "--help"])
    assert rc == 0 and "--preset" in out and "tiny" in out
    assert "torch" not in loaded                    # one subcommand's arguments do not load another's
    rc, out, _ = _modules_after_main(["sysid", "--help"])
    assert rc == 0 and all(c in out for c in ("excite", "diagnose", "fit", "report"))
    rc, out, _ = _modules_after_main(["encoder", "train", "--help"])
    assert rc == 0 and "--steps" in out and "--batch-size" in out


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
