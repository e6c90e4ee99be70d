"""Validation harness of the diagnosis (`imugraph bench diagnose`): inject each effect with randomised
parameters and windows into recordings and simulations, hide the label, diagnose, and score.

For every case the effect library's `inject` adds one effect (imugraph.diagnose.effects, realistic ranges
documented per module); the session handed to the diagnoser is renamed and stripped of the injection's
metadata, so nothing but the signals tells which effect it holds. Unmodified sessions are diagnosed as
well (truth "none"). Scores:

    top-1     = fraction of cases whose verdict equals the truth (injected cases; "none" cases apart)
    false "none"-breakers = clean sessions whose verdict is not "none"
    IoU       = |W_true ∩ W_est| / |W_true ∪ W_est| of the windows of windowed effects, over the cases
                whose verdict is the injected effect (the verdict's t_start/t_end)
    shrink    = 1 − gap_after / gap_before on held-out time, as the diagnoser reports it for the verdict
                (and, separately, for the true effect's entry whatever the verdict)
    injected part shrink = the same for the gap the injection ADDED: a global verdict's held-out gap
                net of the clean host's own gap on that channel (`injected_part_shrink`; needs the clean
                runs) — reported beside the shrink, which it does not replace
    log-score shrink of the injected part = the same in the proper score (A4), all channels summed
                (`injected_part_logscore_shrink`; correct global verdicts)

and the confusion matrix (rows: truth, columns: verdict).
"""

from __future__ import annotations

import time
from typing import Callable, Iterable, Optional

import numpy as np

from imugraph.diagnose.effects import EFFECTS
from imugraph.diagnose.effects.base import replace_session
from imugraph.io.session import Session

NONE = "none"


def hide_label(session: Session, case_id: str) -> Session:
    """The session under a neutral name, without the injection's metadata."""
    s = replace_session(session)
    meta = {k: v for k, v in s.meta.items() if k not in ("injected",)}
    return Session(s.t, s.gyr, s.acc, s.mag, s.quat, s.movement, source=f"<harness case {case_id}>",
                   name=f"case_{case_id}", meta=meta)


def interval_iou(a: tuple, b: tuple) -> float:
    """IoU of two time intervals (t_start, t_end); 0 when either is missing or empty."""
    if a is None or b is None or None in a or None in b:
        return 0.0
    inter = max(0.0, min(a[1], b[1]) - max(a[0], b[0]))
    union = max(a[1], b[1]) - min(a[0], b[0])
    return float(inter / union) if union > 0 else 0.0


def _default_diagnose(session: Session):
    from imugraph.diagnose.run import diagnose

    return diagnose(session)


def _as_json(diag) -> dict:
    """A diagnosis (object with to_json, or the diagnosis.json dict) as a dict."""
    return diag.to_json() if hasattr(diag, "to_json") else dict(diag)


def _entry(d: dict, name: str) -> Optional[dict]:
    for e in d.get("effects", []):
        if e.get("name") == name:
            return e
    return None


def run_case(session: Session, truth_name: str, truth: dict, case_id: str, diagnose_fn: Callable) -> dict:
    """Diagnose one (hidden-label) session and score it against its truth."""
    t0 = time.perf_counter()
    d = _as_json(diagnose_fn(hide_label(session, case_id)))
    seconds = time.perf_counter() - t0
    verdict = d.get("verdict", NONE)
    won = _entry(d, verdict) if verdict != NONE else None
    true_entry = _entry(d, truth_name) if truth_name != NONE else None
    effect = EFFECTS.get(truth_name)
    windowed = bool(effect is not None and effect.windowed)
    case = {"case": case_id, "session": session.name, "truth": truth_name, "verdict": verdict,
            "correct": verdict == truth_name, "truth_params": truth.get("params", {}),
            "truth_window": [truth.get("t_start"), truth.get("t_end")] if windowed else None,
            "shrink": None if won is None else won.get("shrink"),
            "true_effect_shrink": None if true_entry is None else true_entry.get("shrink"),
            "gap": d.get("gap"), "seconds": seconds, "iou": None,
            "ranking": [e.get("name") for e in d.get("effects", [])][:3],
            "host": session.name.split("+")[0],
            "won": None if won is None else {**{k: won.get(k) for k in ("channel", "gap_before", "gap_after",
                                                                        "support_fraction")},
                                             "significance": (won.get("params") or {}).get("significance")},
            "host_excess": None if truth_name != NONE else _host_excess(d),
            "loglik": None if won is None else {k: won.get(k) for k in ("loglik_base_per_channel",
                                                                        "loglik_ext_per_channel")},
            "host_loglik": None if truth_name != NONE else _host_loglik(d),
            "scores": _scores(d)}
    if windowed and verdict == truth_name and won is not None:
        case["estimated_window"] = [won.get("t_start"), won.get("t_end")]
        case["iou"] = interval_iou((truth["t_start"], truth["t_end"]), (won.get("t_start"), won.get("t_end")))
    return case


def _scores(d: dict) -> list:
    """Every effect's decision numbers (miss analysis, §S17-H): name, stage, channel, (A2), (A1), the
    log score (A4) and its worst fold, the own-cost shrink (J6), size/threshold, significant, relevant."""
    out = []
    for e in d.get("effects", []):
        s = e.get("size") or {}
        folds = e.get("own_cost_gain_per_fold") or e.get("loglik_gain_per_fold") or []
        out.append({"name": e.get("name"), "stage": e.get("stage"), "channel": e.get("channel"),
                    "penalised": e.get("penalised_shrink"), "shrink": e.get("shrink"),
                    "loglik_gain": e.get("loglik_gain"),
                    "own_gain": e.get("own_cost_gain"), "min_fold": min(folds) if folds else None,
                    "size": s.get("value"), "threshold": s.get("threshold"), "unit": s.get("unit"),
                    "significant": e.get("significant"), "relevant": e.get("relevant"),
                    "support_fraction": e.get("support_fraction"), "t_start": e.get("t_start"),
                    "t_end": e.get("t_end")})
    return out


def _host_excess(d: dict) -> dict:
    """channel → the held-out gap excess (A1) of an unmodified recording on that channel (the `gap_before`
    of any global effect scored on it): the host's own misfit, which no injected effect's model removes."""
    out = {}
    for e in d.get("effects", []):
        gb = e.get("gap_before")
        if e.get("support_fraction", 1.0) >= 1.0 and gb is not None and np.isfinite(gb):
            out.setdefault(e.get("channel"), float(gb))
    return out


def _host_loglik(d: dict) -> dict:
    """effect name → channel → the base model's held-out log score (A4) ℓ_base of an unmodified
    recording, as scored beside that (global) effect (the rows scored depend on the effect's NaN rows)."""
    return {e.get("name"): dict(e.get("loglik_base_per_channel") or {}) for e in d.get("effects", [])
            if e.get("support_fraction", 1.0) >= 1.0 and e.get("loglik_base_per_channel")}


def injected_part_logscore_shrink(case: dict, hosts: dict) -> Optional[float]:
    """The injected-part shrink in the proper score (A4) (docs/diagnose.md §4, issue 5 G2 (c)): for a
    correct global verdict, with ℓ the held-out score in nats per sample summed over the channels,

        1 − max(0, ℓ_ext(case) − ℓ_base(host)) / (ℓ_base(case) − ℓ_base(host))

    — the fraction of the log-score loss the injection added that the extended model removes, the clean
    host's own misfit (ℓ_base(host), the same samples, the same effect's rows) taken as the floor; every
    channel counts, so a correction that makes another channel worse pays for it. None for a localised
    verdict (scored on its support, which the host's numbers do not cover), a miss, or no host."""
    won, ll = case.get("won"), case.get("loglik")
    if not case.get("correct") or not won or not ll or (won.get("support_fraction") or 1.0) < 1.0:
        return None
    host = ((hosts.get(case.get("host")) or {}).get(case.get("verdict"))) or {}
    base, ext = ll.get("loglik_base_per_channel") or {}, ll.get("loglik_ext_per_channel") or {}
    chans = [c for c in base if c in ext and c in host
             and all(np.isfinite(float(v[c])) for v in (base, ext, host))]
    if not chans:
        return None
    added = sum(float(base[c]) - float(host[c]) for c in chans)
    left = sum(float(ext[c]) - float(host[c]) for c in chans)
    return float(1.0 - max(0.0, left) / added) if added > 0 else None


def criterion_shrink(case: dict, host_ll: dict) -> Optional[float]:
    """The shrink in the units of the criterion that made the verdict significant (S15, docs/diagnose.md
    §S15; reported BESIDE the (A1) shrink, which it does not replace): for an effect judged by the held-out
    log score (time_offset (T6): a delay's residual τ ḣ is motion-locked and small beside a hand's linear
    acceleration, so (G1)'s shape and colour barely change, while the proper score sees it) the log-score
    shrink of the injected part (A5, `injected_part_logscore_shrink`); for every other correct verdict the
    reported shrink ((A1), or (J6) for a jointly fitted gyro effect). None for a miss."""
    if not case.get("correct"):
        return None
    if (case.get("won") or {}).get("significance") == "log_score":
        return injected_part_logscore_shrink(case, host_ll)
    return case.get("shrink")


def injected_part_shrink(case: dict, hosts: dict) -> Optional[float]:
    """Shrink of the part of the gap the injection added (docs/diagnose.md §4): for a global verdict,
    1 − max(0, after − h) / (before − h), h the clean host's own held-out excess on the verdict's channel
    (`_host_excess`); a localised verdict (A3) is already scored above the recording's own gap outside its
    support, so its shrink stands. None when the host was not diagnosed or the injection added nothing."""
    won = case.get("won")
    if not case.get("correct") or not won or won.get("gap_before") is None:
        return None
    if (won.get("support_fraction") or 1.0) < 1.0:
        return case.get("shrink")
    h = (hosts.get(case.get("host")) or {}).get(won.get("channel"))
    b, a = won.get("gap_before"), won.get("gap_after")
    if h is None or a is None or not b > h:
        return None
    return float(1.0 - max(0.0, a - h) / (b - h))


def run_harness(sessions: Iterable, effects: Optional[Iterable[str]] = None, n_per_effect: int = 2,
                rng: Optional[np.random.Generator] = None, *, clean: bool = True,
                diagnose_fn: Optional[Callable] = None, progress: Optional[Callable[[str], None]] = None,
                only: Optional[Iterable[str]] = None, hosts: str = "random") -> dict:
    """Inject, diagnose blind, score (module doc).

    Args:
        sessions: Sessions to inject into (recordings of undisturbed motion and/or simulations); each
            case draws its host from them (`hosts`).
        effects: effect names (default: the whole library).
        n_per_effect: injected cases per effect.
        rng: random generator of the injections (parameters, windows).
        clean: also diagnose every session unmodified (truth "none").
        diagnose_fn: session → diagnosis (object with `to_json` or the diagnosis.json dict); default
            `imugraph.diagnose.run.diagnose`.
        progress: optional callable(str) for one line per case.
        only: case ids ("001", ...) to diagnose; the others are still drawn (same random sequence, so a
            case is replayed exactly) but not diagnosed nor scored. None: all.
        hosts: "random" (default): each case's host session is drawn from `rng` (uniformly among
            `sessions`, before its injection), so an effect meets different hosts and the confusion
            matrix is not one host's story; "cycle": the cases cycle through the sessions in order (the
            pairing effect → host is then fixed by the order of the effects).

    Returns:
        report dict: "cases", "labels", "confusion" (truth → verdict → count), "top1", "n_injected",
        "clean_flagged", "n_clean", "iou" and "shrink" summaries, "seconds".
    """
    from imugraph.errors import SessionError

    sessions = list(sessions)
    if not sessions:
        raise SessionError("<harness>", "sessions", "none", "at least one session")
    names = list(effects) if effects is not None else list(EFFECTS)
    rng = rng or np.random.default_rng(0)
    if hosts not in ("random", "cycle"):
        raise SessionError("<harness>", "hosts", repr(hosts), "'random' or 'cycle'")
    fn = diagnose_fn or _default_diagnose
    say = progress or (lambda _m: None)
    keep = None if only is None else {str(c).zfill(3) for c in only}
    cases = []
    t0 = time.perf_counter()
    for cid, _host, injected, name, truth in draw_cases(sessions, names, n_per_effect, rng, hosts):
        if keep is not None and cid not in keep:
            continue
        case = run_case(injected, name, truth, cid, fn)
        cases.append(case)
        say(_case_line(case))
    k = len(names) * n_per_effect                        # the clean cases' ids follow the injected ones
    if clean:
        for base in sessions:
            k += 1
            if keep is not None and f"{k:03d}" not in keep:
                continue
            case = run_case(base, NONE, {}, f"{k:03d}", fn)
            cases.append(case)
            say(_case_line(case))
    return summarise(cases, names, time.perf_counter() - t0)


def draw_cases(sessions: list, names: Iterable[str], n_per_effect: int, rng: np.random.Generator,
               hosts: str = "random"):
    """The harness' injected cases in order, drawn from `rng` exactly as `run_harness` draws them (host, then
    injection; every case drawn, so a replay of one case id sees the same random sequence): yields
    (case id "001", …, host session, injected session, effect name, truth)."""
    k = 0
    for name in names:
        for _ in range(n_per_effect):
            if hosts == "random" and len(sessions) > 1:
                base = sessions[int(rng.integers(len(sessions)))]
            else:
                base = sessions[k % len(sessions)]
            k += 1
            injected, truth = EFFECTS[name].inject(base, rng)
            yield f"{k:03d}", base, injected, name, truth


def summarise(cases: list, names: list, seconds: float = float("nan")) -> dict:
    """Confusion matrix and scores of a list of scored cases (see `run_harness`)."""
    labels = list(names) + [NONE]
    for c in cases:
        if c["verdict"] not in labels:
            labels.append(c["verdict"])
    confusion = {t: {p: 0 for p in labels} for t in labels}
    for c in cases:
        confusion[c["truth"]][c["verdict"]] += 1
    injected = [c for c in cases if c["truth"] != NONE]
    clean = [c for c in cases if c["truth"] == NONE]
    ious = [c["iou"] for c in injected if c["iou"] is not None]
    shrinks = [c["shrink"] for c in injected if c["correct"] and c["shrink"] is not None]
    true_shrinks = [c["true_effect_shrink"] for c in injected if c["true_effect_shrink"] is not None]
    hosts = {c.get("host"): c.get("host_excess") for c in clean if c.get("host_excess")}
    part = [injected_part_shrink(c, hosts) for c in injected]
    host_ll = {c.get("host"): c.get("host_loglik") for c in clean if c.get("host_loglik")}
    part_ll = [injected_part_logscore_shrink(c, host_ll) for c in injected]
    by_criterion = [criterion_shrink(c, host_ll) for c in injected]

    def stats(v):
        v = [x for x in v if x is not None and np.isfinite(x)]
        return {"n": len(v), "median": float(np.median(v)) if v else None,
                "mean": float(np.mean(v)) if v else None, "min": float(np.min(v)) if v else None}

    return {"cases": cases, "labels": labels, "confusion": confusion,
            "n_injected": len(injected),
            "top1": float(np.mean([c["correct"] for c in injected])) if injected else None,
            "n_clean": len(clean), "clean_flagged": int(sum(not c["correct"] for c in clean)),
            "iou": stats(ious), "shrink": stats(shrinks), "true_effect_shrink": stats(true_shrinks),
            "injected_part_shrink": stats(part), "injected_part_logscore_shrink": stats(part_ll),
            "criterion_shrink": stats(by_criterion),
            "seconds": seconds}


def _case_line(c: dict) -> str:
    extra = f" IoU {c['iou']:.2f}" if c.get("iou") is not None else ""
    sh = f" shrink {c['shrink']:.2f}" if c.get("shrink") is not None else ""
    return (f"case {c['case']} {c['session']}: truth {c['truth']} → {c['verdict']}"
            f"{' ✓' if c['correct'] else ' ✗'}{sh}{extra} ({c['seconds']:.1f} s)")


def format_report(report: dict) -> str:
    """Plain-text confusion matrix and summary lines."""
    labels = report["labels"]
    short = {lab: lab[:10] for lab in labels}
    width = max(len(lab) for lab in labels) + 2
    head = " " * width + " ".join(f"{short[p]:>10}" for p in labels)
    lines = ["confusion matrix (rows: truth, columns: verdict)", head]
    for t in labels:
        row = report["confusion"][t]
        if sum(row.values()) == 0:
            continue
        lines.append(f"{t:<{width}}" + " ".join(f"{row[p]:>10d}" for p in labels))
    top1 = report["top1"]
    lines.append(f"top-1: {'n/a' if top1 is None else f'{100 * top1:.0f} %'} of {report['n_injected']} injected cases")
    lines.append(f"clean sessions flagged (verdict ≠ none): {report['clean_flagged']} of {report['n_clean']}")
    for key, label in (("iou", "window IoU (correct windowed verdicts)"),
                       ("shrink", "gap shrink on held-out time (correct verdicts)"),
                       ("true_effect_shrink", "gap shrink of the true effect (all injected cases)"),
                       ("injected_part_shrink", "gap shrink of the injected part (correct verdicts, net of "
                                                "the clean host's own gap)"),
                       ("injected_part_logscore_shrink", "log-score (A4) shrink of the injected part (correct "
                                                         "global verdicts, net of the clean host's own score)"),
                       ("criterion_shrink", "shrink by the verdict's own criterion (correct verdicts: (A5) for "
                                            "an effect judged by the log score, else the shrink above)")):
        s = report.get(key, {"n": 0})
        if s["n"]:
            lines.append(f"{label}: median {s['median']:.2f}, mean {s['mean']:.2f}, min {s['min']:.2f} (n = {s['n']})")
        else:
            lines.append(f"{label}: none")
    lines.append(f"time: {report['seconds']:.0f} s")
    return "\n".join(lines)
