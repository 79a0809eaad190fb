"""Detector specs ('eigen:30', 'learned:runs/a/model.pt', ...): the one grammar, parsed once. Light on
purpose: argument parsers check specs with it before anything heavy is imported."""

from __future__ import annotations

from dataclasses import dataclass

# The one grammar of detector specs: every command's --detector, the environments' fusion.detector and the
# policy maps' detectors are parsed by `parse_detector`.
# `l3e ate`'s table without --detector: the project's learned detector beside no mask, the
# eigenvalue test at a low and a high threshold (docs/decisions.md) and the labels' own truth
DEFAULT_ATE_DETECTORS = ("none", "learned", "eigen:30", "eigen:110", "oracle")
DETECTOR_GRAMMAR = (
    "none | eigen:<tau> | dcreg:<kappa> | xicp[:<L>] | drpm[:<s>] | oracle[:M] | scanmc[:M] | "
    "learned[-sym][:checkpoint] | "
    "learned+scanmc[:margin]"
)
DETECTOR_KINDS = (
    "none",
    "eigen",
    "dcreg",
    "xicp",
    "drpm",
    "oracle",
    "scanmc",
    "learned",
    "learned-sym",
    "learned+scanmc",
)
# the training-free detectors that read each correspondence: their threshold's default, the published one
XICP_ENOUGH = 300.0  # X-ICP's localizability a direction needs (its published configuration)
DRPM_SNR = 10.0  # DRPM's signal-to-noise factor s
MAP_DETECTORS = DETECTOR_KINDS[1:]  # a localizability map of 'trust everything' says nothing


@dataclass(frozen=True)
class DetectorSpec:
    """A parsed detector spec: its kind and its argument (tau, M, the checkpoint path or the margin;
    None where the spec gives none and the kind's default applies)."""

    kind: str
    tau: float | None = None  # eigen's tau, dcreg's kappa, xicp's localizability, drpm's signal-to-noise factor
    children: int | None = None
    checkpoint: str | None = None
    margin: float | None = None

    @property
    def learned(self) -> bool:
        return self.kind in ("learned", "learned-sym")


# the detectors with one threshold: (default where the spec gives none, the form that gives it, the
# smallest value it may take (exclusive), the rule as the error says it)
THRESHOLDS: dict[str, tuple[float | None, str, float, str]] = {
    "eigen": (None, "the threshold as eigen:<tau>, e.g. eigen:30", 0.0, "the eigenvalue threshold must be positive"),
    "dcreg": (
        None,
        "the condition ratio threshold as dcreg:<kappa>, e.g. dcreg:10",
        1.0,
        "DCReg's condition ratio threshold must exceed 1",
    ),
    "xicp": (XICP_ENOUGH, "the localizability threshold as xicp:<L>, e.g. xicp:300", 0.0, "it must be positive"),
    "drpm": (DRPM_SNR, "the signal-to-noise factor as drpm:<s>, e.g. drpm:10", 0.0, "it must be positive"),
}


def _threshold(spec: str, arg: str, default: float | None, form: str, floor: float, rule: str) -> float:
    """A detector's threshold from its spec's argument, or ValueError naming the form expected."""
    try:
        value = float(arg) if arg or default is None else default
    except ValueError as exc:
        raise ValueError(f"detector '{spec}': give {form}") from exc
    if not floor < value < float("inf"):
        raise ValueError(f"detector '{spec}': {rule}, got {value:g}")
    return value


def parse_detector(spec: str, allowed: tuple[str, ...] = DETECTOR_KINDS, what: str = "detector") -> DetectorSpec:
    """`spec` (see DETECTOR_GRAMMAR) parsed and checked; ValueError naming the problem and the form
    expected. `allowed`: the kinds the caller can use (a map has no use for 'none'), `what` the name the
    error gives the spec."""
    kind, _, arg = spec.partition(":")
    if kind not in DETECTOR_KINDS:
        raise ValueError(f"unknown detector '{spec}' ({DETECTOR_GRAMMAR})")
    if kind not in allowed:
        raise ValueError(f"{what} '{spec}': not usable here (use {', '.join(allowed)})")
    if kind == "none":
        if arg:
            raise ValueError(f"detector '{spec}': 'none' takes no argument")
        return DetectorSpec(kind)
    if kind in THRESHOLDS:
        return DetectorSpec(kind, tau=_threshold(spec, arg, *THRESHOLDS[kind]))
    if kind in ("oracle", "scanmc"):
        if arg and not (arg.isdigit() and int(arg) >= 1):
            raise ValueError(f"detector '{spec}': give the number of children as {kind}:<M>, M >= 1, e.g. {kind}:60")
        return DetectorSpec(kind, children=int(arg) if arg else None)
    if kind == "learned+scanmc":
        try:
            margin = float(arg) if arg else None
        except ValueError as exc:
            raise ValueError(
                f"detector '{spec}': give the margin as learned+scanmc:<log-odds>, e.g. learned+scanmc:1"
            ) from exc
        return DetectorSpec(kind, margin=margin)
    return DetectorSpec(kind, checkpoint=arg or None)


def detector_spec(text: str) -> str:
    """argparse type: a detector spec, refused at parse time with the grammar."""
    import argparse

    try:
        parse_detector(text)
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None
    return text
