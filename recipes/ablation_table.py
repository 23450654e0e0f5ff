"""Collect the result.json files below a folder (e.g. an evaluate.py multirun) into one table and plot.

    python recipes/ablation_table.py eval_out [--out eval_out/ablation] [--force]

Prints a Markdown table (the paper's Table 1 columns) and writes ``ablation.md`` and ``ablation.png``:
each replaces only this command's earlier output (or anything, with ``--force``), checked before either
is written. Bad input (no result.json below the folder, one that is not an evaluation's) is one line and
exit code 2.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from adadex.errors import ConfigError, exit_on_error
from adadex.eval.tables import plot_results, results_table
from adadex.io import atomic_write_text, check_output_file, mark_file
from adadex.modules.channels import parse_channels

#: the kind of output the two files are (their markers, :mod:`adadex.io`)
ABLATION_TABLE = "ablation table"


def main(argv=None) -> str:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("root", type=Path)
    p.add_argument("--out", type=Path, default=None, help="the outputs' path without suffix (default ROOT/ablation)")
    p.add_argument("--force", action="store_true", help="replace files at --out that this command did not write")
    a = p.parse_args(argv)
    files = sorted(a.root.rglob("result.json"))
    if not files:
        raise ConfigError(f"{a.root}: no result.json below it (run recipes/evaluate.py first)")
    out = a.out or a.root / "ablation"
    paths = [check_output_file(out.with_suffix(s), ABLATION_TABLE, force=a.force) for s in (".md", ".png")]
    runs = []
    for f in files:
        try:
            r = json.loads(f.read_text(encoding="utf-8"))
        except (OSError, ValueError) as e:
            raise ConfigError(f"{f}: not readable JSON ({e})") from None
        config = r.get("config") if isinstance(r, dict) else None
        if not isinstance(config, dict) or not all(k in config for k in ("channels", "split", "part", "tracker")) \
                or "summary" not in r:
            raise ConfigError(f"{f}: not a recipes/evaluate.py result (it needs config.channels, config.split, "
                              f"config.part, config.tracker and summary)")
        runs.append(r)
    setting = lambda c: f"{c['split']}/{c['part']}, tracker {Path(str(c['tracker'])).stem}"   # noqa: E731
    settings = {setting(r["config"]) for r in runs}
    results = {}
    for r in sorted(runs, key=lambda r: (len(parse_channels(r["config"]["channels"])), r["config"]["channels"])):
        c = r["config"]
        results[c["channels"] if len(settings) == 1 else f"{c['channels']} ({setting(c)})"] = r["summary"]
    table = results_table(results)
    atomic_write_text(paths[0], table + "\n")
    plot_results(results, paths[1], title="channel ablation" + (f": {settings.pop()}" if len(settings) == 1 else ""))
    for path in paths:
        mark_file(path, ABLATION_TABLE)
    print(table)
    print(f"wrote {out.with_suffix('.md')} and {out.with_suffix('.png')}")
    return table


if __name__ == "__main__":
    with exit_on_error("recipes/ablation_table.py"):
        main()
