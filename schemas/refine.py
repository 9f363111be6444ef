"""Configuration of the ``refine-3dgs`` flow: free views as pseudo ground truth for a
per-scene 3D Gaussian reconstruction, measured on held-out views (METHOD.md "Downstream uses",
3DGS refinement; docs/REFINE.md).

An *arm* is one way of training on a scene: the baseline (captured views only) or a refined
run that adds pseudo views on a schedule. Every arm of a comparison shares the reconstruction
config, the seed and the step budget; only the view source differs.
"""

from __future__ import annotations

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

from .recon import ReconConfig

# Arms the flow knows (ablations as settings). A refined arm may name its weight rule:
# "wiou@reference" is the wiou arm with the authors' weights whatever `weight_rule` says.
ARM_KINDS = ("baseline", "baseline+time", "wiou", "random", "raw", "fixed", "fixed+conf",
             "progressive", "oracle")
ARM_DOC = {
    "baseline": "captured (training) views only",
    "baseline+time": "the baseline given the refined arms' extra CPU seconds as extra steps "
                     "(its step count = max_iterations x the slowest refined arm's CPU seconds "
                     "/ the baseline's, same seed; runs after them)",
    "wiou": "stored free views, lowest WIoU to the training views first (the paper's order)",
    "random": "the same number of stored free views, chosen at random",
    "raw": "the free views in the paper's order, but the raw render of the store's "
           "reconstruction at the same pose instead of the stored (rectified) image",
    "fixed": "as raw, each render fixed by the fixer (`fixer`) with the nearest training "
             "photos warped in: the fixed image is the pseudo ground truth",
    "fixed+conf": "as fixed, each pixel's loss weighted by the fixer's confidence times the "
                  "observed map (render alpha, or a valid warp)",
    "progressive": "as fixed+conf, but each schedule point renders its views from the model "
                   "being trained, nearest ring first (highest WIoU to the training views "
                   "first, stepping outward)",
    "oracle": "ceiling (procedural scenes only): the oracle's true image at the same poses, "
              "in the paper's order",
}
FIXED_ARMS = ("fixed", "fixed+conf", "progressive")

# alpha_fv = hi for BRISQUE/100 <= b_lo, lo for >= b_hi, linear between.
WEIGHT_RULES = {
    "reference": (0.6, 0.1),  # the authors' released code
    "paper": (0.5, 0.3),      # the paper's text: alpha_fv in [0.3, 0.5]
}


def refine_recon_config() -> ReconConfig:
    """The default step budget of a comparison, sized to a shared 2-core CPU: the fast
    reconstruction preset with a fixed number of steps (no plateau stop, no time limit), so
    baseline and refined arms take exactly the same number of optimisation steps. 300 steps:
    the budget docs/REFINE.md measured (about 1-2 min per arm on the shared machine)."""
    return ReconConfig.fast().model_copy(update={"max_iterations": 300, "min_iterations": 300,
                                                 "densify_until": 250, "max_seconds": None})


class RefineConfig(BaseModel):
    """One refinement comparison (applied to every scene)."""

    model_config = ConfigDict(extra="forbid")

    recon: ReconConfig = Field(
        default_factory=refine_recon_config,
        description="The reconstruction trainer's config shared by every arm. Set "
        "min_iterations = max_iterations (the default) so every arm runs exactly the same "
        "number of steps; a plateau stop would give the arms different budgets.")
    arms: list[str] = Field(
        default_factory=lambda: ["baseline", "wiou"],
        description="Arms to run per scene and seed: " + "; ".join(
            f"{k}: {v}" for k, v in ARM_DOC.items()) + ". 'oracle' is skipped on scenes "
        "without an oracle (real scenes). A refined arm may carry its weight rule after "
        "'@' (e.g. 'wiou@reference'); without one it uses `weight_rule`.")
    seeds: list[int] = Field(default_factory=lambda: [0], description="Training seeds; every "
                             "arm runs once per seed.")

    # ------------------------------------------------------------------ schedule (paper)
    every_steps: int = Field(
        3_000, ge=1, description="Paper: free views join every 3k of 30k steps. Scaled to the "
        "budget when it is smaller: interval = round(every_steps * max_iterations / "
        "paper_iterations), at least 1 (300 steps -> every 30).")
    paper_iterations: int = Field(30_000, ge=1, description="Step budget the paper's interval "
                                  "refers to (3DGS: 30k).")
    per_step: int = Field(5, ge=1, description="Free views that join at each schedule point "
                          "(paper: 5).")
    max_free_views: int | None = Field(
        None, ge=0, description="Stop adding after this many free views (None: until the "
        "schedule or the stored free views run out).")
    wiou_reduce: Literal["max", "mean"] = Field(
        "max", description="WIoU of a free view to the training views: the max over training "
        "views (views.parquet `wiou_to_train`) or the mean of its graph edges to them.")

    # ------------------------------------------------------------------ loss of a free view
    weight_rule: Literal["reference", "paper", "constant"] = Field(
        "reference", description="alpha_fv from BRISQUE/100 b: 'reference' (authors' code): "
        "0.6 for b < 0.3, 0.1 for b > 0.5, linear between; 'paper' (the paper's text): 0.5 .. "
        "0.3 over the same range; 'constant': `alpha_constant`. Default 'reference': it "
        "measured better than 'paper' (real scenes, seed 0: -0.07 vs -0.11 dB; procedural: "
        "equal), docs/REFINE.md.")
    brisque_lo: float = Field(0.3, ge=0, le=1, description="b at or below which alpha is "
                              "the rule's high value.")
    brisque_hi: float = Field(0.5, ge=0, le=1, description="b at or above which alpha is "
                              "the rule's low value.")
    alpha_constant: float = Field(0.5, ge=0, description="alpha_fv of the 'constant' rule.")

    # ------------------------------------------------------------------ the fixer
    fixer: str | None = Field(
        None, description="fixer.pt of the fixed arms and of `post_fix` (freescale "
        "train-fixer); None: the shipped checkpoint. Use one that never saw the scene.")
    post_fix: bool = Field(
        False, description="Also score every arm's held-out renders after the fixer (nearest "
        "training photos warped in): the `post` columns, an image operation on the output, "
        "reported beside the model's own scores.")

    # ------------------------------------------------------------------ evaluation
    oracle_views: int = Field(
        12, ge=0, description="Procedural scenes: also score every arm against the oracle at "
        "this many poses off the captured path (candidates that were not kept: NMS-suppressed "
        "or quality-rejected, evenly spaced), none of which any arm trains on.")

    @model_validator(mode="after")
    def _check(self) -> "RefineConfig":
        if self.brisque_hi <= self.brisque_lo:
            raise ValueError(f"brisque_hi {self.brisque_hi} must exceed brisque_lo "
                             f"{self.brisque_lo}")
        for a in self.arms:
            kind, _, rule = a.partition("@")
            if kind not in ARM_KINDS or (rule and (kind.startswith("baseline") or rule not in
                                                   (*WEIGHT_RULES, "constant"))):
                raise ValueError(f"unknown arm {a!r}: expected one of {ARM_KINDS}, optionally "
                                 f"with @reference, @paper or @constant (not on baseline)")
        if len(set(self.arm_names())) != len(self.arms) or not self.arms:
            raise ValueError(f"arms must be a non-empty list without repeats, got {self.arms}")
        if len(set(self.seeds)) != len(self.seeds) or not self.seeds:
            raise ValueError(f"seeds must be a non-empty list without repeats, got {self.seeds}")
        return self

    def arm_names(self) -> list[str]:
        """Arms with their weight rule resolved (``wiou`` -> ``wiou@paper``); the baseline
        has none. These are the arms' folder names."""
        return [a if "@" in a or a.startswith("baseline") else f"{a}@{self.weight_rule}"
                for a in self.arms]

    def interval(self) -> int:
        """Steps between schedule points at this budget."""
        n = self.recon.max_iterations
        if n >= self.paper_iterations:
            return self.every_steps
        return max(1, int(round(self.every_steps * n / self.paper_iterations)))

    def schedule(self) -> list[int]:
        """Steps at which free views join: ``interval, 2 interval, ...`` strictly before the
        last step (a view added at the last step would never be trained on)."""
        k = self.interval()
        return list(range(k, self.recon.max_iterations, k))

    def alpha(self, brisque: float, rule: str | None = None) -> float:
        """alpha_fv of a free view with BRISQUE/100 ``brisque`` (NaN: the rule's midpoint)
        under ``rule`` (default: ``weight_rule``)."""
        rule = rule or self.weight_rule
        if rule == "constant":
            return float(self.alpha_constant)
        hi, lo = WEIGHT_RULES[rule]
        b = float(brisque)
        if b != b:  # NaN: no score stored
            return 0.5 * (hi + lo)
        t = min(max((b - self.brisque_lo) / (self.brisque_hi - self.brisque_lo), 0.0), 1.0)
        return hi + t * (lo - hi)
