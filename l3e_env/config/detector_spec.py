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
    "none | eigen:<tau> | dcreg:<kappa> | oracle[:M] | scanmc[:M] | learned[-sym][:checkpoint] | "
    "learned+scanmc[:margin]"
)
DETECTOR_KINDS = ("none", "eigen", "dcreg", "oracle", "scanmc", "learned", "learned-sym", "learned+scanmc")
MAP_DETECTORS = DETECTOR_KINDS[1:]  # a localizability map of 'trust everything' says nothing


@dataclass(frozen=True)
class DetectorSpec:
    """A parsed detector spec: its kind and its argument (tau, M, the checkpoint path or the margin;
    None where the spec gives none and the kind's default applies)."""

    kind: str
    tau: float | None = None  # eigen's tau, dcreg's kappa
    children: int | None = None
    checkpoint: str | None = None
    margin: float | None = None

    @property
    def learned(self) -> bool:
        return self.kind in ("learned", "learned-sym")


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
    if kind == "eigen":
        try:
            tau = float(arg)
        except ValueError as exc:
            raise ValueError(f"detector '{spec}': give the threshold as eigen:<tau>, e.g. eigen:30") from exc
        if not tau > 0:
            raise ValueError(f"eigenvalue threshold must be positive, got {tau}")
        return DetectorSpec(kind, tau=tau)
    if kind == "dcreg":
        try:
            kappa = float(arg)
        except ValueError as exc:
            raise ValueError(
                f"detector '{spec}': give the condition ratio threshold as dcreg:<kappa>, e.g. dcreg:10"
            ) from exc
        if not kappa > 1:
            raise ValueError(f"detector '{spec}': DCReg's condition ratio threshold must exceed 1")
        return DetectorSpec(kind, tau=kappa)
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
