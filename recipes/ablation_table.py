"""Collect the result.json files below a folder (e.g. an evaluate.py multirun) into one table and plot.

    python recipes/ablation_table.py eval_out [--out eval_out/ablation]

Prints a Markdown table (the paper's Table 1 columns) and writes ``ablation.md`` and ``ablation.png``.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from adadex.eval.tables import plot_results, results_table
from adadex.io import atomic_write_text
from adadex.modules.channels import parse_channels


def main(argv=None) -> str:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("root", type=Path)
    p.add_argument("--out", type=Path, default=None)
    a = p.parse_args(argv)
    files = sorted(a.root.rglob("result.json"))
    if not files:
        raise SystemExit(f"{a.root}: no result.json below it (run recipes/evaluate.py first)")
    runs = [json.loads(f.read_text()) for f in files]
    setting = lambda c: f"{c['split']}/{c['part']}, tracker {Path(str(c['tracker'])).stem}"   # noqa: E731
    settings = {setting(r["config"]) for r in runs}
    results = {}
    for r in sorted(runs, key=lambda r: (len(parse_channels(r["config"]["channels"])), r["config"]["channels"])):
        c = r["config"]
        results[c["channels"] if len(settings) == 1 else f"{c['channels']} ({setting(c)})"] = r["summary"]
    table = results_table(results)
    out = a.out or a.root / "ablation"
    atomic_write_text(out.with_suffix(".md"), table + "\n")
    plot_results(results, out.with_suffix(".png"),
                 title="channel ablation" + (f": {settings.pop()}" if len(settings) == 1 else ""))
    print(table)
    print(f"wrote {out.with_suffix('.md')} and {out.with_suffix('.png')}")
    return table


if __name__ == "__main__":
    main()
