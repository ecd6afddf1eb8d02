"""Temperature feedforward: the tilt a logged temperature causes, taken out at the piezo
before the loop has to see it.

A model that names a temperature path to the tilt (`[plant.thermal]`, a fitted
`temperature_coupling`) says tilt = k x lag(T). The piezo tilts the table by
`tilt_per_v` per volt, so adding gain x lag(T) with gain = -k / tilt_per_v to the command
cancels it; a path is a gain [V/K] and one or two first-order lags in series, as the model
writes them (`leveler tune --suggest --model` designs them).

Why it is built this way:

* Only changes matter. The loop's integral holds every constant, so the output is zeroed
  when the loop engages or the paths change (it adds nothing at that moment: bumpless),
  and from then on follows the temperature's changes through the lags.
* It moves only when a reading arrives (every `[thermometer] interval_s`), so the log's
  environment record of that cycle holds both the temperature and the new output.
* A thermometer that stops answering holds the output where it was; when readings come
  back after more than `resume_after_s` the lags start again from the new reading,
  continuing the held output, rather than taking the temperature's whole change as one
  step (a 10 min outage at 50 V/K could otherwise kick the piezo by volts).
* Each lag is exact for a temperature held between readings, the form the simulated stand
  and the fitted coupling use.
"""

from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass(frozen=True, slots=True)
class FeedforwardPath:
    """gain [V/K] x the temperature through lags of lag_s and lag2_s [s] in series
    (0: none)."""

    gain_v_per_k: float
    lag_s: float = 0.0
    lag2_s: float = 0.0

    def __post_init__(self) -> None:
        if not math.isfinite(self.gain_v_per_k):
            raise ValueError(f"feedforward gain must be finite, got {self.gain_v_per_k!r}")
        for name in ("lag_s", "lag2_s"):
            value = getattr(self, name)
            if not 0.0 <= value < math.inf:
                raise ValueError(f"feedforward {name} must be finite and >= 0, got {value!r}")

    @property
    def lags_s(self) -> tuple[float, ...]:
        return tuple(lag for lag in (self.lag_s, self.lag2_s) if lag > 0)


@dataclass(frozen=True, slots=True)
class Feedforward:
    """The configured paths, summed."""

    paths: tuple[FeedforwardPath, ...]

    def describe(self) -> str:
        return "; ".join(
            f"{p.gain_v_per_k:+.4g} V/K" + "".join(f" through {lag:g} s" for lag in p.lags_s)
            for p in self.paths)


class FeedforwardFilter:
    """The paths' lag states and the output [V] they add to the command."""

    __slots__ = ("_gains", "_input", "_lags", "_t_s", "_y", "_zero", "feedforward",
                 "resume_after_s", "v")

    def __init__(self, feedforward: Feedforward, resume_after_s: float) -> None:
        self.feedforward = feedforward
        self.resume_after_s = resume_after_s
        self._gains = [p.gain_v_per_k for p in feedforward.paths]
        self._lags = [p.lags_s for p in feedforward.paths]
        self._y: list[list[float]] | None = None  # per path, each lag's output [K]
        self._t_s = math.nan  # the last reading's time
        self._input = math.nan  # the last reading [K] (a path without lags takes it as is)
        self._zero = 0.0
        self.v = 0.0  # what the filter adds to the command now

    @property
    def started(self) -> bool:
        return self._y is not None

    def _raw(self) -> float:
        assert self._y is not None
        return sum(g * (y[-1] if y else self._input)
                   for g, y in zip(self._gains, self._y, strict=True))

    def feed(self, t_s: float, temperature_k: float) -> float:
        """Take a reading made at loop time t_s; returns the new output [V]."""
        gap = t_s - self._t_s
        if self._y is None or not gap <= self.resume_after_s:
            # first reading, or back after an outage: the lags settle at this temperature
            # and the output goes on from where it was held
            self._input = temperature_k
            self._y = [[temperature_k] * len(lags) for lags in self._lags]
            self._zero = self._raw() - self.v
        else:
            self._input = temperature_k
            for lags, y in zip(self._lags, self._y, strict=True):
                x = temperature_k
                for j, lag in enumerate(lags):
                    y[j] += -math.expm1(-gap / lag) * (x - y[j])
                    x = y[j]
        self._t_s = t_s
        self.v = self._raw() - self._zero
        return self.v

    def rezero(self) -> None:
        """Add nothing from here (an engage): only later changes of the temperature count."""
        if self._y is not None:
            self._zero = self._raw()
        self.v = 0.0
