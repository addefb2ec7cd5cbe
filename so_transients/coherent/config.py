"""The coherent mode's settings: keys of ``transient_find``'s YAML block, kept apart from the
paper mode's (:class:`so_transients.detect.find.FindConfig`).

Both dataclasses read the same ``calc`` block (:data:`FIND_CONFIGS`,
:func:`so_transients.common.step_config.from_yaml_parts`): a key belongs to the one that
declares it, and a key neither declares is refused.
"""
from __future__ import annotations

from dataclasses import dataclass

from so_transients.common.step_config import ConfigError, from_yaml_parts, positive, share, setting
from so_transients.coherent.joint import DEFAULT_INDICES
from so_transients.coherent.sweep_stack import StackSettings
from so_transients.coherent.vetoes import Vetoes
from so_transients.detect.find import FindConfig


@dataclass
class CoherentConfig:
    coherent_threshold: float = setting(4.5, "Z", "coherent mode: Z of a maximum, in measured spreads")
    row_step: float = setting(0.8, "beam sigma", "coherent mode: beam sigmas between rows of positions")
    max_single_share: float = setting(
        0.5, "",
        "coherent veto: a maximum one detector makes more than this share of is removed")
    max_instant_share: float = setting(
        0.5, "",
        "coherent veto: a maximum the detectors crossed at one instant make more than this share of is "
        "removed (a cosmic ray)")
    chi2_bins: int = setting(
        6, "",
        "coherent veto: chi-squared test over this many detector groups (0: no test)")
    chi2_tail: float = setting(1e-3, "", "chi-squared test: the share of noise maxima it fails")
    chi2_mismatch: float = setting(0.15, "", "chi-squared test: model error allowed, as a share of Z")
    hit_reach: float = setting(
        2.0, "beam sigma",
        "coherent mode: a candidate's hits are the detectors within this many beam sigmas")
    stack_window: float | None = setting(
        None, "s",
        "sweep stacking: crossings within this window are stacked (null: no sweep stacking)")
    stack_seed: float = setting(
        3.0, "Z",
        "sweep stacking: stacks start from single-crossing maxima this high")
    stack_max_share: float = setting(
        0.7, "",
        "sweep stacking: no crossing may make more than this share of a stack's sum")
    joint_bands: bool = setting(
        False, "",
        "coherent mode: a group holding both bands of a dichroic wafer (subobs use: [wafer_slot]) is "
        "searched with the joint-band statistic J (docs: the coherent search)")
    spectral_indices: tuple = setting(DEFAULT_INDICES, "", "joint_bands: J is maximised over these")

    def __post_init__(self):
        positive("transient_find", coherent_threshold=self.coherent_threshold,
                 row_step=self.row_step, max_single_share=self.max_single_share,
                 max_instant_share=self.max_instant_share, hit_reach=self.hit_reach,
                 stack_window=self.stack_window, stack_seed=self.stack_seed,
                 stack_max_share=self.stack_max_share)
        share("transient_find", max_single_share=self.max_single_share,
              max_instant_share=self.max_instant_share, stack_max_share=self.stack_max_share)
        self.spectral_indices = tuple(float(a) for a in self.spectral_indices)
        if not self.spectral_indices:
            raise ConfigError("transient_find: spectral_indices must list at least one index")
        if self.chi2_bins == 1 or self.chi2_bins < 0 or not 0 < self.chi2_tail < 1 \
                or not self.chi2_mismatch >= 0:
            raise ConfigError(f"transient_find: chi2_bins must be 0 (no test) or 2 or more, "
                              f"chi2_tail in (0, 1) and chi2_mismatch 0 or more; got "
                              f"{self.chi2_bins}, {self.chi2_tail}, {self.chi2_mismatch}")

    @property
    def vetoes(self) -> Vetoes:
        """The coherent mode's glitch vetoes."""
        return Vetoes.of(self)

    @property
    def stacking(self) -> StackSettings | None:
        """Sweep stacking's settings (with ``stack_window``), or None."""
        return StackSettings.of(self) if self.stack_window else None


#: ``transient_find``'s config dataclasses, in the order :func:`find_settings` returns them
FIND_CONFIGS = (FindConfig, CoherentConfig)


def find_settings(calc, step="transient_find") -> tuple[FindConfig, CoherentConfig]:
    """``transient_find``'s ``calc`` block (``step``: how errors name it) as its paper-mode
    and coherent-mode settings."""
    return from_yaml_parts(FIND_CONFIGS, calc, step)


def stacking_of(find: FindConfig, coherent: CoherentConfig) -> StackSettings | None:
    """Sweep stacking's settings when ``transient_find`` runs in coherent mode with a
    ``stack_window``, else None."""
    return coherent.stacking if find.mode == "coherent" else None
