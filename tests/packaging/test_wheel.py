"""The wheel carries what adadex ships: installed outside the checkout, the demo and the encoder run.

The wheel is installed with ``pip install --target`` into a temporary folder and run from a
temporary working directory with that folder first on ``PYTHONPATH``, so the package, its assets
and its console entry point come from the wheel, not from this checkout; the heavy dependencies
(torch, mujoco) come from the test's own environment.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def installed(tmp_path_factory) -> dict:
    work = tmp_path_factory.mktemp("wheel")
    subprocess.run([sys.executable, "-m", "pip", "wheel", str(ROOT), "--no-deps", "--no-build-isolation",
                    "-q", "-w", str(work / "dist")], check=True, cwd=work)
    wheel = next((work / "dist").glob("adadex-*.whl"))
    target = work / "site"
    subprocess.run([sys.executable, "-m", "pip", "install", "--no-deps", "-q", "--target", str(target), str(wheel)],
                   check=True, cwd=work)
    run_dir = work / "run"
    run_dir.mkdir()
    env = {**os.environ, "PYTHONPATH": str(target), "OMP_NUM_THREADS": "1"}
    return {"target": target, "cwd": run_dir, "env": env}


def _python(installed, code: str) -> str:
    out = subprocess.run([sys.executable, "-c", code], cwd=installed["cwd"], env=installed["env"],
                         capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stderr[-3000:]
    return out.stdout


def test_installed_package_is_the_wheels(installed):
    where = _python(installed, "import adadex; print(adadex.__file__)").strip()
    assert Path(where).resolve().is_relative_to(installed["target"].resolve()), where
    for parts in (("robot", "robot.xml"), ("encoder", "encoder.pt"), ("encoder", "latents.npz"),
                  ("recordings", "demo.npz")):
        assert (installed["target"] / "adadex" / "assets").joinpath(*parts).is_file(), parts


def test_wheel_loads_the_shipped_encoder_and_robot(installed):
    out = _python(installed, (
        "from adadex.envs.latent import SHIPPED_ENCODER, EncoderLatents\n"
        "from adadex.modules.encoder import load_encoder\n"
        "from adadex.sim.robot import ROBOT_MJCF\n"
        "import mujoco\n"
        "model, meta = load_encoder(SHIPPED_ENCODER)\n"
        "print(SHIPPED_ENCODER)\n"
        "print(EncoderLatents()('mug_00').shape)\n"
        "print(mujoco.MjModel.from_xml_path(str(ROBOT_MJCF)).nu)\n"))
    path, shape, nu = out.split("\n")[:3]
    assert Path(path).resolve().is_relative_to(installed["target"].resolve())
    assert shape == "(64,)" and nu == "22"


def test_wheel_runs_the_sysid_demo(installed):
    out_dir = installed["cwd"] / "demo"
    res = subprocess.run([sys.executable, "-c", "import sys; from adadex.cli import main; sys.exit(main())",
                          "sysid", "demo", "--out", str(out_dir)],
                         cwd=installed["cwd"], env=installed["env"], capture_output=True, text=True, timeout=900)
    assert res.returncode == 0, res.stderr[-3000:]
    assert (out_dir / "report.html").is_file() and (out_dir / "patch.json").is_file()
