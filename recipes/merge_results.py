"""Merges the results of runs split over seeds, sessions or machines, and writes their joint summary and plot.

Every GridWorld recipe writes ``<out_dir>/results.csv`` (one row per episode). Runs that cover different seeds
(``"seeds=[0,1,2]"`` here, ``"seeds=[3,4,5]"`` there) or different conditions can be merged into one file, with
``summary.md`` (Student-t intervals over all seeds, paired comparisons against ``A``) and ``curves.png`` beside it. A cell present in two inputs is
kept once if identical and refused if not.

    python recipes/merge_results.py outputs/explore outputs/explore_b outputs/explore_c --out outputs/explore_all \
        --title "Four rooms: exploration"
"""
import argparse
import logging
from pathlib import Path

from torchrl_options.experiments import merge_results
from torchrl_options.experiments.gridworld import write_summary


def main(argv=None) -> str:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("inputs", nargs="+", help="recipe output directories (or results.csv files)")
    parser.add_argument("--out", required=True, help="directory of the merged results.csv, summary.md, curves.png")
    parser.add_argument("--title", default="Merged results")
    parser.add_argument("--final-window", type=int, default=100, help="episodes of the final return")
    parser.add_argument("--smooth-window", type=int, default=50, help="moving average of the reach criterion")
    parser.add_argument("--curve-window", type=int, default=50, help="moving average of the plotted curves")
    parser.add_argument("--order", default="A,H1u,H1s,H2u,H2s",
                        help="the conditions' order in the tables and legends (others follow alphabetically)")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(message)s")
    sources = [Path(p) / "results.csv" if Path(p).is_dir() else Path(p) for p in args.inputs]
    out = Path(args.out)
    added = merge_results(out / "results.csv", sources)
    summary = write_summary(
        out / "results.csv", out, args.title,
        {"final_window": args.final_window, "smooth_window": args.smooth_window, "curve_window": args.curve_window},
        condition_order=[c.strip() for c in args.order.split(",") if c.strip()],
    )  # fmt: skip
    print(summary)
    print(f"{len(added)} cells merged; results.csv, summary.md and curves.png in {out}")
    return summary


if __name__ == "__main__":
    main()
