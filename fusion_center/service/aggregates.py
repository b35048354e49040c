"""Running aggregates of a run: what the summary needs, in memory that does not grow with the
number of cycles (issue 10: a long-running centre kept every record and latency sample).

* :class:`LatencyHistogram`: a fixed-size log-spaced histogram (1 µs .. 100 s, 2 % relative
  bin width, 930 bins) with exact count, min, max and sum; a percentile is the upper edge of
  its bin clamped to [min, max], so it is within 2 % of the exact order statistic.
* :class:`RunAggregates`: counters over the records (decisions, agreement of the decision and
  of every rule with the truth, degraded cycles, cycles with clipped readings, the stages run in any cycle (``stages_run``,
  in pipeline order),
  ``nodes_by_state`` totals), fed one record at a time.
"""

from __future__ import annotations

import math
from collections import Counter


STAGE_ORDER = ("fusion", "forces", "area", "contact_type", "slip")  # service.pipeline's order


def _stage_rank(stage: str) -> tuple[int, str]:
    return (STAGE_ORDER.index(stage) if stage in STAGE_ORDER else len(STAGE_ORDER), stage)


class LatencyHistogram:
    """Fixed-size histogram of durations in ms (log-spaced bins); thread-unsafe by itself
    (the service adds under its evaluation lock)."""

    LOW_MS = 1e-3
    HIGH_MS = 1e5
    RATIO = 1.02

    def __init__(self):
        self._log_ratio = math.log(self.RATIO)
        self.bins = int(math.ceil(math.log(self.HIGH_MS / self.LOW_MS) / self._log_ratio)) + 2
        self.counts = [0] * self.bins  # [0]: below LOW_MS, [-1]: at or above HIGH_MS
        self.count = 0
        self.total = 0.0
        self.min: float | None = None
        self.max: float | None = None

    def _bin(self, ms: float) -> int:
        if ms < self.LOW_MS:
            return 0
        if ms >= self.HIGH_MS:
            return self.bins - 1
        return 1 + min(self.bins - 3, int(math.log(ms / self.LOW_MS) / self._log_ratio))

    def add(self, ms: float) -> None:
        if not math.isfinite(ms):
            return
        self.counts[self._bin(ms)] += 1
        self.count += 1
        self.total += ms
        self.min = ms if self.min is None or ms < self.min else self.min
        self.max = ms if self.max is None or ms > self.max else self.max

    def percentile(self, q: float) -> float | None:
        """The q-th percentile (nearest rank), within one bin (2 %) of the exact value."""
        if not self.count:
            return None
        rank = min(self.count, max(1, math.ceil(q / 100.0 * self.count)))
        seen = 0
        for index, c in enumerate(self.counts):
            seen += c
            if seen >= rank:
                if index == 0:
                    upper = self.min  # below the resolution (1 µs)
                elif index == self.bins - 1:
                    upper = self.max
                else:
                    upper = self.LOW_MS * self.RATIO ** index
                return min(max(upper, self.min), self.max)
        return self.max

    @property
    def mean(self) -> float | None:
        return self.total / self.count if self.count else None


class RunAggregates:
    """What the run summary says about the records, updated per record (no record kept)."""

    def __init__(self):
        self.records = 0
        self.errors = 0
        self.decisions = Counter({"H1": 0, "H0": 0, "undecided": 0})
        self.with_truth = 0
        self.correct = 0
        self.rule_names: list[str] | None = None
        self.rule_decided: Counter = Counter()
        self.rule_agree: Counter = Counter()
        self.degraded = 0
        self.over_range = 0   # cycles with readings clipped at a packed limit code (over_range_nodes)
        self.stages_run: list[str] = []
        self._stages_seen: set[str] = set()
        self.undecided_by_integrity = 0
        self.node_state_cycles: Counter = Counter()  # state -> node-cycles in that state

    def add(self, record: dict) -> None:
        self.records += 1
        if "decision" not in record:
            self.errors += 1
            return
        decision = record["decision"]
        self.decisions[decision] += 1
        truth = record.get("truth")
        if truth is not None and decision != "undecided":
            self.with_truth += 1
            self.correct += decision == truth
        rules = record.get("rules") or {}
        if not self.rule_names and rules:  # the first record with rules (cycle 0 may have none)
            self.rule_names = list(rules)
        if truth is not None:
            for name in self.rule_names or ():
                verdict = rules.get(name, {}).get("decision")
                if verdict in ("H1", "H0"):
                    self.rule_decided[name] += 1
                    self.rule_agree[name] += verdict == truth
        if record.get("degraded"):
            self.degraded += 1
        if record.get("over_range_nodes"):
            self.over_range += 1
        for stage in record.get("stages_run") or ():
            if stage not in self._stages_seen:
                self._stages_seen.add(stage)
                # pipeline order, whatever cycle ran a stage first (a cycle with no PDO runs
                # neither fusion nor contact type: the summary does not depend on which ones)
                self.stages_run = sorted(self._stages_seen, key=_stage_rank)
        for state, nodes in (record.get("nodes_by_state") or {}).items():
            self.node_state_cycles[state] += len(nodes)

    def agree_with_truth(self) -> str | None:
        return f"{self.correct}/{self.with_truth}" if self.with_truth else None

    def rules_agree_with_truth(self) -> dict[str, str]:
        return {name: f"{self.rule_agree[name]}/{self.rule_decided[name]}" for name in self.rule_names or ()}
