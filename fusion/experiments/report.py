"""The report folder's text: ``report.md`` (tables, figures inline) from the ``results.json`` content."""

from __future__ import annotations

from fusion.evaluate import PAPER_TABLE1, Accuracy, markdown_table

#: Display name -> key of the paper's Table 1.
PAPER_KEYS = {"CNN fusion (normals cue)": "cnn", "SVM (normals cue)": "svm", "kNN (normals cue)": "knn"}


def pct(acc: dict | None) -> str:
    """'98.3 % [97.9, 98.7]' from an accuracy dict (or '-')."""
    return Accuracy(**acc).percent() if acc else "-"


def table1(rows: list[dict]) -> list[dict]:
    """Table-1 rows: classifier, our guided / blind accuracy (95 % interval), the paper's."""
    out = []
    for clf in dict.fromkeys(r["classifier"] for r in rows):
        by = {r["strategy"]: r for r in rows if r["classifier"] == clf}
        paper = PAPER_TABLE1.get(PAPER_KEYS.get(clf, ""))
        out.append({"classifier": clf,
                    "guided": pct(by.get("guided", {}).get("accuracy")),
                    "blind": pct(by.get("blind", {}).get("accuracy")),
                    "paper guided": f"{paper[0]:.2f} %" if paper else "-",
                    "paper blind": f"{paper[1]:.2f} %" if paper else "-",
                    "train s (guided)": by.get("guided", {}).get("fit_seconds", "-"),
                    "inference ms/seq": by.get("guided", {}).get("predict_ms_per_sequence", "-")})
    return out


def pivot(rows: list[dict], keys: tuple[str, ...], cell, *, column: str = "k", head=lambda v: f"K={v}") -> list[dict]:
    """Rows of a results table: one per distinct ``keys`` tuple of ``rows`` (in order of first appearance), holding
    those key fields, then a column ``head(v)`` per sorted value ``v`` of ``rows``' field ``column``; the cell is
    ``cell(row)`` of the first row with that key and value, or '-' where there is none."""
    values = sorted({r[column] for r in rows})
    out = []
    for key in dict.fromkeys(tuple(r[f] for f in keys) for r in rows):
        row = dict(zip(keys, key))
        for v in values:
            hit = [r for r in rows if tuple(r[f] for f in keys) == key and r[column] == v]
            row[head(v)] = cell(hit[0]) if hit else "-"
        out.append(row)
    return out


def touches_table(rows: list[dict], setting: str) -> list[dict]:
    """K columns per (classifier, strategy, rule) of one setting."""
    out = pivot([r for r in rows if r["setting"] == setting], ("classifier", "strategy", "rule"),
                lambda r: pct(r["accuracy"]))
    for row in out:
        row["rule"] = "sum of log" if row["rule"] == "log" else "sum"
    return out


def difference_table(rows: list[dict], group: str) -> list[dict]:
    """Paired differences (percentage points, 95 % interval, smallest detectable) as rows per ``group`` value
    (pose or strategy) and classifier, K columns."""
    return pivot(rows, (group, "classifier"), _difference)


def _difference(d: dict | None) -> str:
    """'+3.1 [-0.5, +6.8] (+-4.2)' in percentage points, or '-'."""
    if not d:
        return "-"
    return f"{100 * d['difference']:+.1f} [{100 * d['low']:+.1f}, {100 * d['high']:+.1f}] (+-{100 * d['detectable']:.1f})"


def noise_table(rows: list[dict], kind: str) -> list[dict]:
    """Accuracy per level (columns) of one noise kind, a row per (pose, classifier, strategy)."""
    sel = [{"pose": "upright", **r} for r in rows if r["kind"] == kind]
    return pivot(sel, ("pose", "classifier", "strategy"), lambda r: pct(r["accuracy"]), column="level",
                 head=lambda v: f"{v:g}")


def _image(name: str, caption: str) -> str:
    return f"![{caption}]({name})"


def render(results: dict) -> str:
    """The whole ``report.md``."""
    lines = [f"# {results.get('title', 'visuotactile reproduce')}", ""]
    lines += [f"Command: `{results['command']}`  ", f"Data: `{results['data']}`  ",
              (f"Date: {results['date']}; machine: {results['machine']}; seed {results['seed']}"
              f"{' (quick)' if results.get('quick') else ''}."), "",
              "Accuracies are percentages with a 95 % percentile-bootstrap interval (1000 resamples, seeded): "
              + results["bootstrap"], ""]
    paper = results.get("paper")
    if paper:
        lines += ["## Paper protocol (Table 1)", "",
                  (f"{len(paper['objects'])} objects of {len(paper['classes'])} classes "
                  f"({', '.join(paper['classes'])}), {paper['contours']} contours per object and strategy, "
                  f"{paper['test_fraction']:.0%} of each strategy's sequences held out at random (by sequence, "
                  "as in the paper: the same objects are in training and test). Interval: bootstrap over test "
                  "sequences, not objects: the question here is the paper's (new contours of known objects), and "
                  "its 3 objects per class would give an interval of little use; the unseen-objects part below "
                  "bootstraps over objects."), "",
                  (f"Objects: {', '.join(paper['objects'])} (the first classes in sorted order unless named, and "
                   "the first instances of each by file name: a fixed rule, not chosen by results)."), "",
                  markdown_table(table1(paper["rows"])), ""]
        lines += [_image(f, f) for f in paper.get("figures", [])] + [""]
    unseen = results.get("unseen")
    if unseen:
        lines += ["## Unseen objects", "",
                  (f"{unseen['n_objects']} objects of {len(unseen['classes'])} classes, {unseen['contours']} "
                  f"contours per test object and strategy ({unseen.get('train_contours', unseen['contours'])} per "
                  f"training object); grouped {unseen['folds']}-fold by object (a test object is "
                  "never in training), out-of-fold predictions of every sequence. One touch per decision; "
                  "interval: bootstrap over objects. One model per fold and classifier, trained on the training "
                  "objects as stored, on their contours of every strategy together: the strategies differ only in "
                  "the contours that touch the test objects."), "",
                  "### Upright (as stored)", "", markdown_table(table1(unseen["rows"])), ""]
        if unseen.get("any_pose_rows"):
            lines += ["### Any pose", "",
                      ("The same test objects, each turned by its own seeded uniformly random rotation applied to "
                       "the raw mesh before loading; the same models."), "",
                      markdown_table(table1(unseen["any_pose_rows"])), ""]
        for key, group, title, what in (
                ("strategy_differences", "pose", "Guided minus blind", "guided - blind"),
                ("pose_differences", "strategy", "Any pose minus upright", "any pose - upright")):
            if unseen.get(key):
                lines += [f"### {title}", "",
                          (f"Accuracy difference {what} in percentage points, paired object by object (each "
                           "object's share of right K-touch decisions, log rule), 95 % bootstrap interval over "
                           "objects, and in brackets the smallest difference this design detects with 80 % power "
                           "at the 5 % level."), "", markdown_table(difference_table(unseen[key], group)), ""]
        lines += [_image(f, f) for f in unseen.get("figures", [])] + [""]
    touches = results.get("touches")
    if touches:
        lines += ["## K touches per decision", "",
                  ("K distinct contours of the same test object are classified and their probabilities fused "
                  "(sum of log probabilities, or the paper's sum); disjoint groups per object. Interval: "
                  "bootstrap over objects."), ""]
        for setting in dict.fromkeys(r["setting"] for r in touches["rows"]):
            lines += [f"### {setting.replace('_', ' ')}", "", markdown_table(touches_table(touches["rows"], setting)),
                      ""]
        lines += [_image(touches["figure"], "accuracy vs K"), ""]
    noise = results.get("noise")
    if noise:
        lines += ["## Noise", "",
                  "The unseen-objects models (trained on clean data) on the objects they never saw (each fold's "
                  f"test objects, each in its random pose), along contours of their own ({noise['contours']} per "
                  "object and strategy, the same contours at every level) read with: "
                  + "; ".join(f"{k}: {v}" for k, v in noise["kinds"].items())
                  + ". Interval: bootstrap over objects.", ""]
        for kind in dict.fromkeys(r["kind"] for r in noise["rows"]):
            lines += [f"### {kind.replace('_', ' ')} ({noise['kinds'].get(kind, '')})", "",
                      markdown_table(noise_table(noise["rows"], kind)), ""]
        lines += [_image(noise["figure"], "accuracy vs noise"), ""]
    attention = results.get("attention")
    if attention:
        rows = [{"pose": r.get("pose", "upright"), "strategy": r["strategy"], "attention": r["attention"],
                 "classifier": r["classifier"], "K=1": pct(r["accuracy_k1"]), f"K={r['k']}": pct(r["accuracy_k"]),
                 f"minus blind, K={r['k']}": _difference(r.get("minus_blind_k")),
                 "saliency s/object": r["saliency_seconds_per_object"] if r["saliency_seconds_per_object"]
                 is not None else "-", "note": r.get("note", "")} for r in attention["rows"]]
        lines += ["## Attention models compared", "",
                  (f"Paper objects, {attention['contours']} contours per object per strategy, grouped "
                  f"{attention['folds']}-fold by object (unseen objects), trained as stored and tested upright and "
                  "in any pose; interval: bootstrap over objects; 'minus blind': paired difference in percentage "
                  "points over objects, 95 % interval, and (+-) the smallest difference the design detects. "
                  "Saliency time: median over the first object of each class."), "", markdown_table(rows), ""]
    runtime = results.get("runtime")
    if runtime:
        pts = runtime["points"]
        table = [{"configuration": p["label"], "error": f"{100 * p['error']:.1f} %", "accuracy": pct(p["accuracy"]),
                  "any pose": "-" if p.get("accuracy_any_pose") is None else pct(p["accuracy_any_pose"]),
                  "s / decision": f"{p['seconds']:.4f}", "touch s / contour": f"{p['touch_seconds_per_contour']:.4f}",
                  "inference s / seq": f"{p['inference_seconds_per_sequence']:.5f}",
                  "saliency s / object": f"{p['saliency_seconds_per_object']:.2f}",
                  "front": "yes" if p["on_front"] else ""} for p in sorted(pts, key=lambda p: p["seconds"])]
        named = [f"- **{name}**: {pts[i]['label']}: error {100 * pts[i]['error']:.1f} %, "
                 f"{pts[i]['seconds']:.4f} s per decision" for name, i in runtime["named"].items()]
        lines += ["## Recognition error against run time per decision", "",
                  (f"Paper objects, {runtime['contours']} contours per object and strategy per (probes, grid); "
                  f"split: {runtime['split']}; pose-free classifiers trained on the objects as stored, tested on "
                  "the held-out ones upright and ('any pose') each in its seeded random rotation, whose accuracy "
                  "is shown beside; the front is over upright errors. Time per decision = K x (touching one "
                  "contour + inference on one "
                  "sequence), measured on this machine; guided contours also need the object's saliency once "
                  "(stated separately, not included). Fusion rule: sum of log probabilities."), "",
                  "Operating points on the Pareto front:", "", *named, "",
                  _image(runtime["figure"], "Pareto front"), "", markdown_table(table), ""]
        for f in runtime.get("failures", []):
            lines.append(f"- not measured: {f['classifier']} {f['strategy']} P{f['probes']} G{f['grid']}: {f['error']}")
    lines += _calibration_lines(results)
    if results.get("active"):
        from fusion.experiments.active import render_markdown as active_markdown

        lines += active_markdown(results["active"]).splitlines() + [""]
    lines += ["## Sizes", "", "```", *(f"{k}: {v}" for k, v in results["sizes"].items()), "```", "",
              "Wall time of each part in the run that wrote this report (s; a resumed part reuses its cache): "
              + ", ".join(f"{k} {v:.0f}" for k, v in results.get("seconds", {}).items()), ""]
    return "\n".join(lines)


def _calibration_lines(results: dict) -> list[str]:
    """The calibration and open-set sections (:mod:`fusion.experiments.openset`), when they ran."""
    from fusion.experiments.openset import calibration_table, openset_table, rejected_by_class_lines

    lines = []
    cal = results.get("calibration")
    if cal:
        lines += ["## Calibrated posteriors", "",
                  (f"{cal['n_objects']} objects, {cal['contours']} contours each ({cal['strategy']}), grouped folds by "
                   "object; each fold's temperature and tempered-rule dependence fitted on objects held out inside "
                   "its training folds; tested on the fold's objects in any pose. ECE (15 bins) with a 95 % "
                   "bootstrap interval over objects; K touches of one object per decision."), "",
                  markdown_table(calibration_table(cal["rows"])), "",
                  markdown_table(cal["fits"]), ""] + [_image(f, f) for f in cal["figures"]] + [""]
    ops = results.get("openset")
    if ops:
        lines += ["## Objects of classes never trained on", "",
                  (f"Classes rotated out of training ({len(ops['left_out'])} rotations: "
                   + "; ".join(", ".join(c) for c in ops["left_out"])
                   + f"), {ops['strategy']}, any pose. AUROC known vs unknown [95 % bootstrap over objects]; for "
                   "the score the training folds chose ('chosen'): share of known decisions kept and of unknown "
                   "ones answered unknown at the thresholds fitted on training data (leaving classes out inside "
                   "it); '@95 % test-known': unknown rejected at the threshold keeping 95 % of the test's known."
                   + (f" CNNs among the classifiers train with outlier exposure on the touches of {ops['outliers']} objects of no "
                      "class here." if ops.get("outliers") else "")
                   + (f" Their hidden layers also train with a supervised contrastive term (weight {ops['contrastive']})."
                      if ops.get("contrastive") else "")),
                  "", markdown_table(openset_table(ops["rows"])), ""]
        by_class = rejected_by_class_lines(ops["rows"])
        if by_class:
            lines += [" ".join(by_class), ""]
    return lines


__all__ = ["difference_table", "noise_table", "pct", "render", "table1", "touches_table"]
