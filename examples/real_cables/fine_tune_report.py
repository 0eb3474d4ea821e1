"""Gather the leave-one-out and fine-tuning runs into a table and a figure.

    python examples/real_cables/fine_tune_report.py [runs/leave_one_out] [NAME]

Reads OUT/<cable>/eval (zero-shot) and OUT/<cable>/fine-<n>/{train,eval} (fine_tune_curve.sh)
and writes, beside this script, NAME.json, NAME.md and NAME.png (NAME: fine_tune_curve; a
NAME with "code" in it titles the figure for learning the new cable's code alone): per
cable, the eval score against the number of the new cable's train recordings fine-tuned on
(0: zero-shot), beside freezing the cable, the per-cable `mlp-long` model trained from
scratch on all of them (results.json, mean of its seeds) and DEFORM's published per-cable
score.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

HERE = Path(__file__).parent
CABLES = ("DLO1", "DLO2", "DLO3", "DLO4")
DEFORM = dict(zip(CABLES, (1.01, 0.97, 0.77, 0.85), strict=True))  # Chen et al. 2024, Table 1


def _read(path: Path) -> dict:
    return json.loads(path.read_text())


def collect(out: Path) -> dict:
    """Per cable: zero-shot, each fine-tune's score, recordings and seconds, the references."""
    per_cable = _read(HERE / "results.json")
    rows = {}
    for cable in CABLES:
        run = out / cable
        if not (run / "eval" / "summary.json").is_file():
            continue
        zero = _read(run / "eval" / "summary.json")
        fine = {}
        for path in sorted(run.glob("fine-*/eval/summary.json")):
            name = path.parent.parent.name.removeprefix("fine-")
            train = _read(path.parent.parent / "train" / "summary.json")
            fine[name] = {"score_cm": _read(path)["model_score_cm"],
                          "recordings": train["train_episodes"],
                          "train_seconds": train["seconds"]}  # fmt: skip
        rows[cable] = {
            "zero_shot_cm": zero["model_score_cm"],
            "fine_tuned": dict(sorted(fine.items(), key=lambda kv: kv[1]["recordings"])),
            "freeze_cm": zero["freeze_score_cm"],
            "per_cable_mlp_long_cm": round(per_cable[cable]["mlp-long"]["mean_cm"], 4),
            "deform_cm": DEFORM[cable],
        }
    return rows


def table(rows: dict) -> str:
    counts = sorted({f["recordings"] for r in rows.values() for f in r["fine_tuned"].values()})
    head = ["cable", "freeze", "zero-shot"] + [f"{n} rec." for n in counts]
    head += ["per-cable `mlp-long` (all rec.)", "DEFORM (all rec.)"]
    lines = ["| " + " | ".join(head) + " |", "|---" + "|---:" * (len(head) - 1) + "|"]
    for cable, r in rows.items():
        by_count = {f["recordings"]: f["score_cm"] for f in r["fine_tuned"].values()}
        cells = [cable, f"{r['freeze_cm']:.2f}", f"{r['zero_shot_cm']:.2f}"]
        cells += [f"{by_count[n]:.2f}" if n in by_count else "–" for n in counts]
        cells += [f"{r['per_cable_mlp_long_cm']:.2f}", f"{r['deform_cm']:.2f}"]
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def figure(rows: dict, path: Path, how: str = "fine-tuned") -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.5, 4))
    for cable, r in rows.items():
        fine = list(r["fine_tuned"].values())
        x = [0] + [f["recordings"] for f in fine]
        y = [r["zero_shot_cm"]] + [f["score_cm"] for f in fine]
        (line,) = ax.plot([max(v, 0.5) for v in x], y, "o-", label=cable)
        ax.axhline(r["per_cable_mlp_long_cm"], color=line.get_color(), ls="--", lw=0.8)
    ax.set_xscale("log", base=2)
    ticks = sorted({max(v, 0.5) for r in rows.values() for v in
                    [0] + [f["recordings"] for f in r["fine_tuned"].values()]})  # fmt: skip
    ax.set_xticks(ticks, ["0\n(zero-shot)" if t == 0.5 else str(int(t)) for t in ticks])
    ax.set_xlabel("the new cable's train recordings fine-tuned on")
    ax.set_ylabel("eval score (cm, 5 s open loop)")
    ax.set_title(f"A model trained on the other three cables, {how}\n"
                 "(dashed: per-cable mlp-long trained from scratch on all recordings)",
                 fontsize=9)  # fmt: skip
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


def main(out: Path, name: str = "fine_tune_curve") -> None:
    rows = collect(out)
    (HERE / f"{name}.json").write_text(json.dumps(rows, indent=1) + "\n")
    (HERE / f"{name}.md").write_text(table(rows))
    how = "its code learned" if "code" in name else "fine-tuned"
    figure(rows, HERE / f"{name}.png", how)
    print(table(rows))


if __name__ == "__main__":
    main(Path(sys.argv[1] if len(sys.argv) > 1 else "runs/leave_one_out"), *sys.argv[2:3])
