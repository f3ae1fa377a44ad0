"""Closed-loop precision search: the cheapest quantized cell whose success is decided not worse than full precision.

    candidates = [Candidate.from_ref(ref) for ref in refs]          # cost from the committed layer index
    result = precision_search(candidates, decide, SearchDesign(alpha=0.05, margin_pp=5))
    result.chosen, result.table(), result.episodes_spent, result.episodes_exhaustive

A candidate is an ordinary cell (`<benchmark>/<suite>/<model>/<method>-<preset>-<scope>[-<subset>]`): its
allocation quantizes the layers its scope and subset select with its preset, and leaves every other layer at full
precision. Its cost is the weight memory of the model under that allocation (`weight_bits`), counted on the
model's committed layer index (`models.layer_index`: the released architecture, so a ratio, not a byte count of
a policy with other widths); the reference is every layer at 16 bits (BF16).

The search visits the candidates cheapest first (ties: more activation bits first, then the lower proxy, e.g. the
per-component layer error a header reports, then the name): proxies only order, episodes decide. Each candidate visited runs the anytime-valid
stopping rule of `vlaquantbench.sequential` against the full-precision cell (`decide`). A `worse` decision prunes
every later candidate at least as aggressive on the same layers (`at_least_as_aggressive`: same quantization
method, a superset of the layers, no more weight bits and no more activation bits); the first `not_worse` ends
the search and is the chosen allocation; `undecided` (the cap) moves on.

A space recorded only in part (a run cut short: the candidates started cheapest first, some not finished) is
searched over the whole space all the same (`unrecorded`: the candidates without finished records; K is the
space's size, never the recorded count): the search gives its answer when the recorded candidates determine it
(every candidate it visits is recorded, and the first `not_worse` ends it before any unrecorded one, which is then
`not reached`), and otherwise raises `SearchUndetermined` naming the unrecorded candidates it would read next.

Guarantee: alpha is split over the K candidates of the space, fixed before any episode (Bonferroni): each
candidate's rule runs at alpha / K whether or not it is visited. A false `not_worse` (true difference at most
-margin) has probability at most alpha / K per candidate, so the chance that any decision of the search, and in
particular the chosen allocation, is a false `not_worse` is at most alpha, whatever the order, the pruning and
the dependence between candidates that share the baseline's episodes. Pruning relies on `worse` decisions only to
skip candidates: a wrong prune or a non-monotone space costs power (a cheaper allocation missed), never the
guarantee; `exhaustive` says whether it did on a fully recorded space.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from vlaquantbench.cells import RTN_ALIASES, parse_cell_name, parse_ref
from vlaquantbench.errors import UserError
from vlaquantbench.quant.presets import FloatFormat, Preset, WeightGrid, parse_preset
from vlaquantbench.sequential import DECISIONS, Design, outcome_rounds, paired_rounds, stopping_rule

if TYPE_CHECKING:
    import pandas as pd

FULL_PRECISION_BITS = 16  # the reference weight memory: every layer in BF16
_ELEMENT_BITS = {"E4M3": 8, "E5M2": 8, "E3M2": 6, "E2M3": 6, "E2M1": 4}
# Bits per element of each block scale: MX's shared E8M0, NVFP4's E4M3 (its FP32 tensor scale is negligible).
_BLOCK_SCALE_BITS = {"mx": (8, 32), "nvfp4": (8, 16)}
SCALE_BITS = 16  # a group's scale (and an asymmetric grid's zero point) stored in 16 bits


def weight_bits(preset: Preset) -> float:
    """Stored bits per weight under `preset`: its elements plus its group or block scales (per-channel and
    per-tensor scales are one number per row or tensor and are left out)."""
    weight = preset.weight
    if weight is None:
        return float(FULL_PRECISION_BITS)
    if isinstance(weight, WeightGrid):
        per_group = SCALE_BITS * (1 if weight.symmetric else 2)
        return weight.bits + (per_group / weight.group_size if weight.group_size else 0.0)
    bits = _ELEMENT_BITS[weight.element]
    if weight.family in _BLOCK_SCALE_BITS:
        scale, block = _BLOCK_SCALE_BITS[weight.family]
        return bits + scale / block
    return float(bits)


def activation_bits(preset: Preset) -> int:
    """Bits of the linear inputs under `preset` (16 where they stay at full precision)."""
    if preset.act_bits is not None:
        return preset.act_bits
    if isinstance(preset.act_format, FloatFormat):
        return _ELEMENT_BITS[preset.act_format.element]
    return FULL_PRECISION_BITS


@dataclass(frozen=True)
class Candidate:
    """One allocation: the cell `ref`, the layers it quantizes (by name) with their parameter counts, and its
    quantizer method and preset. `cost_ratio`: its weight memory over the full-precision model's."""

    ref: str
    method: str
    preset: Preset
    layers: Mapping[str, int]  # quantized layer name -> weight parameters
    model_params: int  # weight parameters of every linear layer of the model
    proxy: float | None = None  # an ordering hint (lower first among equal costs); never a decision

    @classmethod
    def from_ref(cls, ref: str, proxy: float | None = None) -> Candidate:
        """The candidate of the cell `ref`, from its name and the model's committed layer index (no torch)."""
        from vlaquantbench.models.layer_index import linear_params
        from vlaquantbench.quant.patterns import select_names
        from vlaquantbench.quant.subsets import get_subset

        _, _, model, name = parse_ref(ref)
        fields = parse_cell_name(name, ref)
        preset = parse_preset(fields["preset"])
        index = linear_params(model)
        layers: dict[str, int] = {}
        if not preset.is_baseline:
            subset = get_subset(model, fields["subset"]) if fields["subset"] else None
            try:
                selected = select_names({c: list(v) for c, v in index.items()}, fields["scope"],
                                        subset.only if subset else None, subset.exclude if subset else None)
            except UserError as err:
                raise UserError(f"cell {ref!r}: {err}") from None
            for component, names in selected.items():
                layers.update({layer: index[component][layer] for layer in names})
        total = sum(sum(group.values()) for group in index.values())
        # `ablate` is RTN; a calibrated cell (`calib_*`) is RTN after its own smoothing: another method here
        method = "rtn" if fields["method"] in RTN_ALIASES else fields["method"]
        return cls(ref, method, preset, layers, total, proxy)

    @property
    def cost_bits(self) -> float:
        """Weight memory in bits: the quantized layers at `weight_bits(preset)`, every other layer at 16."""
        quantized = sum(self.layers.values())
        return quantized * weight_bits(self.preset) + (self.model_params - quantized) * FULL_PRECISION_BITS

    @property
    def cost_ratio(self) -> float:
        return self.cost_bits / (self.model_params * FULL_PRECISION_BITS)


def at_least_as_aggressive(b: Candidate, a: Candidate) -> bool:
    """Whether `b` quantizes at least what `a` does, at least as coarsely: the same method, every layer of `a`,
    no more weight bits and no more activation bits. Such a `b` is pruned once `a` is decided worse."""
    return (b.method == a.method and set(a.layers) <= set(b.layers)
            and weight_bits(b.preset) <= weight_bits(a.preset)
            and activation_bits(b.preset) <= activation_bits(a.preset))


@dataclass(frozen=True)
class SearchDesign:
    """The search's level over the whole space (alpha) and its margin: `not_worse` means not worse than full
    precision by more than margin_pp points."""

    alpha: float = 0.05
    margin_pp: float = 5.0

    def per_candidate(self, candidates: int) -> Design:
        """The level each candidate's rule runs at: alpha split evenly over the space (checks both values)."""
        Design(self.alpha, self.margin_pp)
        if candidates < 1:
            raise UserError("the search space holds no candidate")
        return Design(self.alpha / candidates, self.margin_pp)

    def guarantee(self, candidates: int) -> str:
        return (f"alpha {self.alpha:g} split over the {candidates} candidates of the space (each rule at "
                f"{self.alpha / candidates:.3g}): the chance that the chosen allocation, or any other decided "
                f"not_worse, is in truth worse than full precision by {self.margin_pp:g} points or more is at "
                f"most {self.alpha:g}")


class SearchUndetermined(UserError):
    """The recorded candidates do not determine the search: it reaches `needed` (candidates without finished
    records, in search order), the first of which it would read next. `result`: the search up to there."""

    def __init__(self, needed: list[str], result: SearchResult):
        self.needed, self.result = needed, result
        rank = next(i for i, c in enumerate(result.order, 1) if c.ref == needed[0])
        decided = ", ".join(f"{ref.rsplit('/', 1)[-1]} {verdict.decision}" for ref, verdict in result.verdicts.items())
        super().__init__(
            f"the search is not determined by the recorded candidates: it reaches {needed[0]} (#{rank} of "
            f"{len(result.order)} in search order), which has no finished records"
            + (f" (decided before it: {decided})" if decided else "")
            + f"; the {len(needed)} candidate(s) without records it may still read: "
            + ", ".join(ref.rsplit("/", 1)[-1] for ref in needed)
            + ". Record them (the run goes on cheapest first) and search again")


@dataclass(frozen=True)
class Verdict:
    """What one candidate's stopping rule decided, and the episodes it read and could have read."""

    decision: str
    episodes_used: int
    episodes_cap: int
    detail: Mapping = field(default_factory=dict)  # e.g. the difference and confidence sequence at the stop

    def __post_init__(self):
        if self.decision not in DECISIONS:
            raise ValueError(f"decision {self.decision!r} is not one of {DECISIONS}")


Decide = Callable[[Candidate, Design], Verdict]


@dataclass
class SearchResult:
    design: SearchDesign
    order: list[Candidate]
    verdicts: dict[str, Verdict]  # visited candidates by reference
    pruned_by: dict[str, str]  # pruned candidate -> the `worse` candidate that pruned it
    chosen: Candidate | None
    episodes_cap: int  # what one candidate run in full costs

    @property
    def episodes_spent(self) -> int:
        return sum(v.episodes_used for v in self.verdicts.values())

    @property
    def episodes_exhaustive(self) -> int:
        """Every candidate of the space run in full."""
        return self.episodes_cap * len(self.order)

    def status(self, ref: str) -> str:
        if ref in self.verdicts:
            return "chosen" if self.chosen is not None and self.chosen.ref == ref else "visited"
        if ref in self.pruned_by:
            return f"pruned by {self.pruned_by[ref]}"
        return "not reached"

    def rows(self) -> list[dict]:
        """One row per candidate in search order: cost, status, decision and episodes read."""
        rows = []
        for rank, candidate in enumerate(self.order, 1):
            verdict = self.verdicts.get(candidate.ref)
            rows.append({"order": rank, "cell": candidate.ref, "cost_ratio": candidate.cost_ratio,
                         "weight_bits": weight_bits(candidate.preset), "layers": len(candidate.layers),
                         "proxy": candidate.proxy, "status": self.status(candidate.ref),
                         "decision": verdict.decision if verdict else "",
                         "episodes_used": verdict.episodes_used if verdict else 0,
                         **(dict(verdict.detail) if verdict else {})})
        return rows


def search_order(candidates: Iterable[Candidate]) -> list[Candidate]:
    """Cheapest first; among equal costs more activation bits first (so that a `worse` prunes the same weights
    with coarser activations), then the lower proxy (none last), then the reference."""
    return sorted(candidates, key=lambda c: (c.cost_bits, -activation_bits(c.preset), c.proxy is None,
                                             c.proxy or 0.0, c.ref))


def _tie(candidate: Candidate) -> tuple[float, int]:
    """What `search_order` ranks by before the proxy: candidates equal in it are ordered by their proxies."""
    return candidate.cost_bits, activation_bits(candidate.preset)


def precision_search(candidates: Iterable[Candidate], decide: Decide, design: SearchDesign,
                     unrecorded: Iterable[str] = ()) -> SearchResult:
    """Visit the candidates in `search_order`, each decided by `decide(candidate, per-candidate design)`, pruning
    after `worse` and stopping at the first `not_worse` (the chosen allocation).

    `unrecorded`: candidates of the space without finished records (never passed to `decide`). Reaching one that
    no `worse` has pruned raises `SearchUndetermined`; so does visiting a recorded candidate that ties with an
    unpruned unrecorded one in cost and activation bits where the recorded candidates carry proxies (their order
    then rests on a proxy the unrecorded one's header has yet to give; without proxies it goes by name).
    Unrecorded candidates after the chosen one are `not reached`."""
    order = search_order(candidates)
    refs = [c.ref for c in order]
    if len(set(refs)) != len(refs):
        raise UserError(f"the search space names a cell twice: {sorted({r for r in refs if refs.count(r) > 1})}")
    missing = set(unrecorded)
    if missing - set(refs):
        raise UserError(f"unrecorded cells outside the search space: {sorted(missing - set(refs))}")
    per_candidate = design.per_candidate(len(order))
    verdicts: dict[str, Verdict] = {}
    pruned_by: dict[str, str] = {}
    worse: list[Candidate] = []
    chosen = None
    cap = 0

    def pruner_of(candidate: Candidate) -> Candidate | None:
        return next((w for w in worse if at_least_as_aggressive(candidate, w)), None)

    def undetermined(at: Candidate) -> SearchUndetermined:
        """The unrecorded candidates the search may still read, from `at`'s tie on (those no `worse` prunes)."""
        partial = SearchResult(design, order, verdicts, pruned_by, None, cap)
        start = next(i for i, c in enumerate(order) if _tie(c) == _tie(at))
        needed = [c.ref for c in order[start:] if c.ref in missing and pruner_of(c) is None]
        return SearchUndetermined(needed, partial)

    proxied = any(c.proxy is not None for c in order)  # a space whose headers give proxies (layer errors)
    for candidate in order:
        pruner = pruner_of(candidate)
        if pruner is not None:
            pruned_by[candidate.ref] = pruner.ref
            continue
        if candidate.ref in missing or proxied and any(c.ref in missing and _tie(c) == _tie(candidate)
                                                       and pruner_of(c) is None for c in order):
            raise undetermined(candidate)
        verdict = decide(candidate, per_candidate)
        verdicts[candidate.ref] = verdict
        cap = max(cap, verdict.episodes_cap)
        if verdict.decision == "worse":
            worse.append(candidate)
        elif verdict.decision == "not_worse":
            chosen = candidate
            break
    return SearchResult(design, order, verdicts, pruned_by, chosen, cap)


def exhaustive(candidates: Iterable[Candidate], decide: Decide, design: SearchDesign) -> tuple[Candidate | None, dict[str, Verdict]]:
    """Every candidate decided (no pruning, no early end) at the same per-candidate level: the cheapest
    `not_worse` in search order, and every verdict. What the search must match when the space is monotone."""
    order = search_order(candidates)
    per_candidate = design.per_candidate(len(order))
    verdicts = {c.ref: decide(c, per_candidate) for c in order}
    chosen = next((c for c in order if verdicts[c.ref].decision == "not_worse"), None)
    return chosen, verdicts


def records_decider(episodes: Mapping[str, pd.DataFrame], headers: Mapping[str, Mapping], baseline: str) -> Decide:
    """Decide candidates from their recorded episodes: the stopping rule on the task-interleaved rounds paired with
    `baseline`'s (what the live runner reads, round for round), with A - B and A's success rate at the stop and
    their confidence sequences at the candidate's level (alpha / K: simultaneous over the space). Records that a
    live rule stopped are accepted only at the search's level and margin, which alone make them the same test."""
    from vlaquantbench.confidence_sequence import contrast_interval, rate_interval

    def decide(candidate: Candidate, design: Design) -> Verdict:
        stopping = headers[candidate.ref].get("stopping")
        if stopping and stopping["rounds_run"] < headers[candidate.ref]["episodes_per_task"]:
            if (stopping["alpha"], stopping["margin_pp"]) != (design.alpha, design.margin_pp):
                raise UserError(f"cell {candidate.ref}: its records were stopped by a live rule at alpha "
                                f"{stopping['alpha']:g} and margin {stopping['margin_pp']:g} pp; the search decides at "
                                f"alpha {design.alpha:.4g} (its alpha over the space's candidates) and margin "
                                f"{design.margin_pp:g} pp: run it in full or at that level")
        differences = paired_rounds(episodes[candidate.ref], episodes[baseline], (candidate.ref, baseline))
        result = stopping_rule(differences, design)
        delta = contrast_interval(differences[: result.rounds_used], design.alpha)
        rate = rate_interval(outcome_rounds(episodes[candidate.ref])[: result.rounds_used], design.alpha)
        detail = {"delta_at_stop_pp": delta.estimate, "delta_cs_low_pp": delta.low, "delta_cs_high_pp": delta.high,
                  "rate_at_stop": rate.estimate, "rate_cs_low": rate.low, "rate_cs_high": rate.high}
        # The cap: the cell's rounds in full (a live rule that stopped it recorded fewer than its config runs)
        cap = max(differences.size, int(headers[candidate.ref].get("episodes_per_task") or 0) * differences.shape[1])
        return Verdict(result.decision, result.episodes_used, cap, detail)

    return decide


def pareto_front(rows: list[dict]) -> set[str]:
    """The decided rows (a `rate_at_stop`) that no other is at least as cheap and at least as successful as, and
    strictly one of them."""
    decided = [r for r in rows if r.get("rate_at_stop") is not None]
    return {r["cell"] for r in decided
            if not any(o["cost_ratio"] <= r["cost_ratio"] and o["rate_at_stop"] >= r["rate_at_stop"]
                       and (o["cost_ratio"], o["rate_at_stop"]) != (r["cost_ratio"], r["rate_at_stop"]) for o in decided)}


def check_live_design(design: SearchDesign, candidates: int, baseline: str, alpha: float, margin_pp: float,
                      against: str) -> None:
    """Cells that a study's live stopping rule (study.sequential: `alpha`, `margin_pp`, `against`) runs are searched
    only when that rule is the search's per-candidate rule: alpha / K, the same margin, against the baseline.
    UserError naming the fields otherwise, before any episode runs."""
    per_candidate = design.per_candidate(candidates)
    if against != baseline.rsplit("/", 1)[-1]:
        raise UserError(f"study.sequential.against is {against}, the search's baseline {baseline}: the candidates "
                        "must stop against the search's baseline")
    if abs(alpha - per_candidate.alpha) > 1e-12 * per_candidate.alpha or margin_pp != design.margin_pp:
        raise UserError(f"study.sequential (alpha {alpha:g}, margin_pp {margin_pp:g}) is not the search's per-candidate "
                        f"rule: set alpha {per_candidate.alpha:.6g} (search.alpha {design.alpha:g} / {candidates} "
                        f"candidates) and margin_pp {design.margin_pp:g}")
