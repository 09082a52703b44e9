"""The chapter-dependency figure of the instructors' page (book/figures/chapter-dependencies.png).

``CHAPTERS`` is the one list of chapters with what each builds on; tests/book checks it
against the table of contents. Run ``python book/figures/chapter_dependencies.py`` to redraw.
"""
from __future__ import annotations

from pathlib import Path

# number: (short title, file stem, chapters it builds on)
CHAPTERS = {
    1: ("Noise and sensors", "01-noise-and-sensors", ()),
    2: ("Kalman filter", "02-kalman-filter-from-scratch", (1,)),
    3: ("Steady state", "03-steady-state-and-frequency", (2,)),
    4: ("Continuous to discrete", "04-continuous-to-discrete", (2,)),
    5: ("Coordinated turns", "05-coordinated-turns", (4,)),
    6: ("Curves in space", "06-curves-in-space", (5,)),
    7: ("EKF", "07-extended-kalman-filter", (5,)),
    8: ("Unscented transform", "08-unscented-transform", (7,)),
    9: ("Consistency", "09-consistency", (8,)),
    10: ("IMM", "10-interacting-multiple-models", (9,)),
    11: ("Drone case study", "11-drone-tracking-case-study", (6, 10)),
    12: ("3-D radar case study", "12-radar-3d-imm-case-study", (6, 10)),
    13: ("GPS fusion", "13-gps-fusion", (7,)),
    14: ("Attitude and height", "14-drone-attitude-and-height", (3,)),
    15: ("Localization to SLAM", "15-robot-localization-to-slam", (7,)),
    16: ("Particle filters", "16-particle-filters", (9,)),
    17: ("Tracking in clutter", "17-tracking-in-clutter", (10,)),
    18: ("Real aircraft", "18-tracking-real-aircraft", (9, 10)),
    19: ("Two engines", "19-two-engines", (9, 18)),
    20: ("Many aircraft", "20-many-aircraft", (17, 18)),
}


def depth(k: int) -> int:
    deps = CHAPTERS[k][2]
    return 0 if not deps else 1 + max(depth(d) for d in deps)


def draw(path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    levels: dict[int, list[int]] = {}
    for k in CHAPTERS:
        levels.setdefault(depth(k), []).append(k)
    pos = {}
    for lev, ks in levels.items():
        for i, k in enumerate(ks):
            pos[k] = (lev, (len(ks) - 1) / 2 - i)
    fig, ax = plt.subplots(figsize=(15, 5), dpi=80)
    for k, (_, _, deps) in CHAPTERS.items():
        for d in deps:
            ax.annotate("", xy=pos[k], xytext=pos[d],
                        arrowprops=dict(arrowstyle="-|>", color="0.45", lw=1.0, shrinkA=26, shrinkB=30))
    for k, (title, _, _) in CHAPTERS.items():
        x, y = pos[k]
        ax.text(x, y, f"{k}\n{title}", ha="center", va="center", fontsize=8,
                bbox=dict(boxstyle="round,pad=0.35", fc="#e8f0fa" if k <= 10 else "#f6efe2", ec="0.4"))
    ax.set_xlim(-0.6, max(levels) + 0.6)
    ax.set_ylim(-1.9, 1.9)
    ax.axis("off")
    ax.set_title("Chapter dependencies (an arrow points from a chapter to one that builds on it)", fontsize=10)
    fig.tight_layout()
    fig.savefig(path)
    plt.close(fig)


if __name__ == "__main__":
    draw(Path(__file__).with_name("chapter-dependencies.png"))
