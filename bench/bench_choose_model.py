# make bench: skip (an experiment over model folders and data given as arguments)
"""Experiment: choose between model folders by a rule fixed before their figures (issue 15).

Two trainings of one recipe that differ only in the seed differ on G_n by as much as most recipe
switches moved it (bench/RESULTS.md), so a shipped model is chosen among seeds — on *validation*
shapes, by a rule written down first, with the test shapes only reported. This script applies that
rule, so a choice can be re-run from the folders alone.

For each candidate (``--candidate NAME=FOLDER``; the first is the incumbent, the model shipped now)
and each set (``--validation``; ``--test`` to report):

* ``evaluate maps`` on the set's ``render-dataset`` folder, with the coarse depth the truth smoothed
  by σ = 2 px and, with the set's ``coarse`` folder (``render-dataset --coarse-shapes``), the shape
  prior's reconstructions: G_n's mean angle against the coarse depth's own normals, the exemplar
  L1 and the appearance-diversity ratio;
* ``compare`` under the rig on ``shapes × views`` of the set's seed: sRGB PSNR / FLIP on the object
  of NGP without and with G_sp^real, and where G_sp^real puts its light and in what hue
  (``added_light_placement``: precision, recall, colour_deg).

Issue 15's goals (``GOALS``) are counted on the validation set. A candidate replaces the incumbent
iff it meets at least as many goals and its NGP FLIP is at most ``--flip-tolerance`` above the
incumbent's; among those, the most goals win, then the lower FLIP. Each measurement is kept in
``--out`` and reused (the script resumes); the table is printed as Markdown for bench/RESULTS.md and
the decision written to ``decision.json``.

    .venv/bin/python bench/bench_choose_model.py --out outputs/bench/choose-car \\
        --candidate shipped=ngp_mi/pretrained/car --candidate seed1=outputs/models/car_s1 \\
        --validation outputs/data/val_car,outputs/data/val_car_coarse,600,10x4 \\
        --test outputs/data/held_out_car,outputs/data/held_out_car_coarse,500,10x4
"""

from __future__ import annotations

import argparse
import json
from dataclasses import dataclass
from pathlib import Path

from ngp_mi.atomic import write_json
from ngp_mi.eval.compare import NGP_METHOD, NO_SP_METHOD, CompareConfig, run_compare
from ngp_mi.eval.maps_eval import evaluate_maps

# issue 15's goals on held-out shapes: key → (what, test on a set's figures)
GOALS = {
    "gn_recon": ("G_n >= 3 deg better than the depth's own normals on reconstructions",
                 lambda f: f["gn_gain_recon"] >= 3.0),
    "gn_sigma2": ("G_n >= 6 deg better on sigma 2 px", lambda f: f["gn_gain_sigma2"] >= 6.0),
    "exemplar": ("exemplar L1 <= 0.04", lambda f: f["exemplar_l1"] <= 0.04),
    "diversity": ("appearance-diversity ratio >= 0.7", lambda f: f["diversity"] >= 0.7),
    "image": ("NGP w/o G_sp^real >= 24 dB and <= 0.15 FLIP (a chairs' goal)",
              lambda f: f["no_sp_psnr"] >= 24.0 and f["no_sp_flip"] <= 0.15),
}


# the figures measure() keeps; a change of what it measures bumps it, and older figures are measured again
# (2: G_sp^real's light's precision, recall and hue)
FIGURES_FORMAT = 2


@dataclass(frozen=True)
class ShapeSet:
    """Held-out shapes: a ``render-dataset`` folder, its reconstructions, and ``compare``'s set."""
    name: str
    data: str
    coarse: str
    seed: int
    shapes: int
    views: int

    @classmethod
    def parse(cls, name: str, text: str) -> "ShapeSet":
        try:
            data, coarse, seed, size = text.split(",")
            shapes, views = size.split("x")
            return cls(name, data, coarse, int(seed), int(shapes), int(views))
        except ValueError:
            raise SystemExit(f"--{name} {text!r}: expected DATA,COARSE_DATA,SEED,SHAPESxVIEWS "
                             "(e.g. outputs/data/val_car,outputs/data/val_car_coarse,600,10x4)") from None


def measure(folder: str, shape_set: ShapeSet, out: Path) -> dict:
    """The goals' figures of one model folder on one set (kept in ``out/figures.json``, reused)."""
    saved = out / "figures.json"
    key = {"model": folder, "set": shape_set.__dict__, "format": FIGURES_FORMAT}
    if saved.exists() and (figures := json.loads(saved.read_text())).get("key") == key:
        return figures
    evals = {name: evaluate_maps(folder, shape_set.data, out / name, **kwargs)
             for name, kwargs in (("sigma2", {"coarse_sigma": 2.0}), ("recon", {"coarse_data": shape_set.coarse}))}
    summary = run_compare(CompareConfig(num_shapes=shape_set.shapes, views=shape_set.views, resolution=64,
                                        light_setups=("rig",), seed=shape_set.seed, maps_checkpoint=folder),
                          out / "compare", log=lambda *_: None)
    rows = {row["method"]: row for row in summary}

    def gain(name: str) -> float:
        errors = evals[name]["normal_error_deg"]
        return errors["from_coarse_depth"]["mean"] - errors["G_n"]["mean"]

    figures = {"key": key, "gn_gain_recon": gain("recon"), "gn_gain_sigma2": gain("sigma2"),
               "gn_recon": evals["recon"]["normal_error_deg"]["G_n"]["mean"],
               "gn_sigma2": evals["sigma2"]["normal_error_deg"]["G_n"]["mean"],
               "exemplar_l1": evals["sigma2"]["albedo_reconstruction_l1"],
               "diversity": evals["sigma2"]["appearance_diversity_ratio"],
               "no_sp_psnr": rows[NO_SP_METHOD]["psnr_srgb_masked"], "no_sp_flip": rows[NO_SP_METHOD]["flip_masked"],
               "ngp_psnr": rows[NGP_METHOD]["psnr_srgb_masked"], "ngp_flip": rows[NGP_METHOD]["flip_masked"],
               **{f"sp_{k}": rows[NGP_METHOD][f"specular_{k}"] for k in ("precision", "recall", "colour_deg")}}
    write_json(saved, figures)
    return figures


def goals_met(figures: dict, goals: list[str]) -> list[str]:
    """The keys of the ``goals`` that ``figures`` meet."""
    return [key for key in goals if GOALS[key][1](figures)]


def choose(validation: dict[str, dict], goals: list[str], flip_tolerance: float) -> tuple[str, str]:
    """The rule: the first name is the incumbent; a candidate with at least as many goals met and
    NGP FLIP within ``flip_tolerance`` of the incumbent's is eligible; the most goals, then the lowest
    FLIP, wins. Returns (the chosen name, why)."""
    names = list(validation)
    incumbent = validation[names[0]]
    count = {name: len(goals_met(figures, goals)) for name, figures in validation.items()}
    eligible = [name for name in names if count[name] >= count[names[0]]
                and validation[name]["ngp_flip"] <= incumbent["ngp_flip"] + flip_tolerance]
    best = min(eligible, key=lambda name: (-count[name], validation[name]["ngp_flip"]))
    why = (f"{best}: {count[best]} goals met against the incumbent's {count[names[0]]}, "
           f"NGP FLIP {validation[best]['ngp_flip']:.3f} against {incumbent['ngp_flip']:.3f} "
           f"(tolerance {flip_tolerance})")
    return best, why


def table(figures: dict[tuple[str, str], dict], goals: list[str]) -> str:
    lines = ["| model | set | G_n on reconstructions: ° (better by) | G_n on σ 2 px | exemplar L1 | diversity "
             "| NGP w/o G_sp^real | NGP | G_sp^real's light: precision / recall / hue error ° | goals met |",
             "|" + "---|" * 10]
    for (name, set_name), f in figures.items():
        lines.append(f"| {name} | {set_name} | {f['gn_recon']:.2f} ({f['gn_gain_recon']:.2f}°) "
                     f"| {f['gn_sigma2']:.2f} ({f['gn_gain_sigma2']:.2f}°) | {f['exemplar_l1']:.3f} "
                     f"| {f['diversity']:.2f} | {f['no_sp_psnr']:.2f} / {f['no_sp_flip']:.3f} "
                     f"| {f['ngp_psnr']:.2f} / {f['ngp_flip']:.3f} "
                     f"| {f['sp_precision']:.2f} / {f['sp_recall']:.2f} / {f['sp_colour_deg']:.1f} "
                     f"| {len(goals_met(f, goals))} of {len(goals)} |")
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--candidate", action="append", required=True, metavar="NAME=FOLDER",
                        help="a model folder or shipped name; the first is the incumbent (alone: measured, no choice)")
    parser.add_argument("--validation", required=True, metavar="DATA,COARSE,SEED,SxV")
    parser.add_argument("--test", metavar="DATA,COARSE,SEED,SxV", help="figures reported, never used to choose")
    parser.add_argument("--goals", default=",".join(GOALS),
                        help=f"the goals counted, comma-separated ({', '.join(GOALS)}; the car's rule leaves out image)")
    parser.add_argument("--flip-tolerance", type=float, default=0.005)
    parser.add_argument("--out", default="outputs/bench/choose-model")
    args = parser.parse_args()
    candidates = dict(item.split("=", 1) for item in args.candidate)
    if any(not name or not folder for name, folder in candidates.items()):
        raise SystemExit("--candidate NAME=FOLDER (the first is the incumbent)")
    goals = [key.strip() for key in args.goals.split(",") if key.strip()]
    unknown = [key for key in goals if key not in GOALS]
    if not goals or unknown:
        raise SystemExit(f"--goals {args.goals!r}: {'unknown ' + ', '.join(unknown) if unknown else 'none given'}; "
                         f"expected some of {', '.join(GOALS)}")
    sets = [ShapeSet.parse("validation", args.validation)] + ([ShapeSet.parse("test", args.test)] if args.test else [])
    out = Path(args.out)
    figures = {}
    for shape_set in sets:
        for name, folder in candidates.items():
            print(f"{shape_set.name}: {name} ({folder})", flush=True)
            figures[name, shape_set.name] = measure(folder, shape_set, out / shape_set.name / name)
    print(table(figures, goals))
    if len(candidates) == 1:  # the incumbent measured ahead of its challengers
        return
    chosen, why = choose({name: figures[name, "validation"] for name in candidates}, goals, args.flip_tolerance)
    print(f"\nchosen by the validation set: {why}")
    write_json(out / "decision.json", {"chosen": chosen, "folder": candidates[chosen], "why": why,
                                       "goals": {key: GOALS[key][0] for key in goals},
                                       "met": {f"{n} / {s}": goals_met(f, goals) for (n, s), f in figures.items()}})


if __name__ == "__main__":
    main()
