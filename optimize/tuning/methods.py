"""Optimisation methods over a flat parameter vector, one step at a time.

Every method is a small state machine over numpy arrays: ``init(x0, seed)``
gives a state (plain Python and numpy, picklable: checkpoints hold it),
``step(state, oracle)`` takes one iteration and returns the new state and a
row for the history, and ``incumbent(state)`` is the parameter vector the
method stands by (what is scored on held-out scenarios). The oracle evaluates
the training objective on a fixed batch:

- ``oracle.value_and_grad(x) -> (f, g)``: one forward and one reverse pass;
- ``oracle.value(x) -> f``, where given: one forward pass, without the
  gradient's reverse pass (L-BFGS's backtracking trials);
- ``oracle.values(X) -> f``: the objective of a population ``X`` (P, n) in
  one batched forward pass (CMA-ES);
- ``oracle.use(k)``, where the oracle can ``renew``: the objective on
  training batch ``k`` from now on (L-BFGS moves to a fresh batch when it has
  converged on its own).

Methods (:data:`METHODS`):

- ``adam`` (and any first-order optax optimiser by name, :class:`FirstOrder`):
  optax on the exact gradient, global-norm clipped, a fresh batch every
  iteration in the tuner;
- ``lbfgs``: limited-memory BFGS (two-loop recursion, memory 10) with a
  backtracking Armijo line search and a cap on the step's length in theta:
  quasi-Newton curvature for a gradient that is steep in a few directions.
  A line search whose first trial was rejected costs a full gradient per
  trial; where the oracle has ``value``, the trials after a rejected one (and
  every trial of the step after a backtracking one) take the value alone and
  the gradient only at the accepted point: the same iterates, fewer reverse
  passes. Converged on its batch (twice in a row no step lowers the cost, or by at most
  ``ftol`` of it: scipy's L-BFGS-B test), it goes on
  from where it stands on a fresh training batch, up to ``renewals`` times,
  where the oracle can renew; then it reports convergence;
- ``cmaes``: CMA-ES (the maintained ``cma`` package), its population
  evaluated as one batch;
- ``cmaes-lbfgs``: CMA-ES for the first generations (a global look around),
  then L-BFGS from its mean.

Example:
  >>> m = get("lbfgs")
  >>> oracle = Oracle(value_and_grad=lambda x: (float(x @ x), 2 * x))
  >>> state = m.init(np.ones(3), seed=0)
  >>> for _ in range(10):
  ...     state, row = m.step(state, oracle)
  >>> float(np.abs(m.incumbent(state)).max()) < 1e-6
  True
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable

import cma
import jax
import jax.numpy as jnp
import numpy as np
import optax

from jaxsync._errors import ConfigError
from jaxsync.optimize.tuning.loop import apply_update, first_order_problem, make_optimizer

BATCH_METHODS = ("lbfgs", "cmaes", "cmaes-lbfgs")
"""The methods that optimise one training batch at a time (a deterministic objective)."""
METHODS = ("adam", *BATCH_METHODS)
"""The methods compared in the tuner benchmark: Adam stands for the first-order optax optimisers."""


@dataclasses.dataclass
class Oracle:
    """The training objective on a fixed batch; counts what it is asked.

    ``renew(k)``, where given, switches the objective to training batch ``k``
    (0 is the batch it starts on); :meth:`use` calls it once per change."""

    value_and_grad: Callable | None = None
    values: Callable | None = None
    renew: Callable | None = None
    value: Callable | None = None
    gradient_calls: int = 0
    value_calls: int = 0  # single-point values (forward only)
    forward_rollouts: int = 0  # population members evaluated
    batch: int = 0

    def use(self, k: int) -> None:
        if k != self.batch:
            self.renew(k)
            self.batch = k

    def vg(self, x):
        self.gradient_calls += 1
        f, g = self.value_and_grad(x)
        return float(f), np.asarray(g, dtype=float)

    def v(self, x):
        self.value_calls += 1
        return float(self.value(x))

    def pop(self, X):
        self.forward_rollouts += len(X)
        return np.asarray(self.values(np.asarray(X)), dtype=float)


# ----------------------------------------------------------------- first order


@dataclasses.dataclass(frozen=True)
class FirstOrder:
    """A first-order optax optimiser on the exact gradient (default: Adam at
    0.05, global-norm clipped at 1). A non-finite value or gradient skips the
    step (the parameters and the optimiser's state are kept). With
    ``fresh_batches`` the tuner gives it a new training batch every iteration
    (``oracle.use``): a stochastic gradient method."""

    optimizer: optax.GradientTransformation = dataclasses.field(
        default_factory=lambda: make_optimizer(0.05, clip_norm=1.0)
    )
    needs = ("value_and_grad",)
    fresh_batches = True

    def init(self, x0, seed: int = 0) -> dict:
        x = np.asarray(x0, dtype=float)
        return {"x": x, "opt": self.optimizer.init(x)}

    def step(self, state, oracle: Oracle):
        f, g = oracle.vg(state["x"])
        row = {"train_cost": f, "grad_norm": float(np.linalg.norm(g)), "accepted": 1}
        u = apply_update(self.optimizer, state["x"], state["opt"], f, g)
        if not bool(u.finite):
            row["accepted"] = 0
            return state, row
        return {"x": np.asarray(u.params, dtype=float), "opt": u.opt_state}, row

    def incumbent(self, state):
        return state["x"]

    def to_data(self, state) -> dict:
        return {"x": state["x"], "opt": [np.asarray(v) for v in jax.tree_util.tree_leaves(state["opt"])]}

    def from_data(self, data) -> dict:
        x = np.asarray(data["x"], dtype=float)
        template = jax.tree_util.tree_structure(self.optimizer.init(x))
        leaves = [jnp.asarray(v) for v in data["opt"]]
        if len(leaves) != template.num_leaves:
            raise ConfigError(
                f"the checkpoint's optimiser state has {len(leaves)} arrays, this optimiser's {template.num_leaves}: "
                "it was written by another optimiser"
            )
        return {"x": x, "opt": jax.tree_util.tree_unflatten(template, leaves)}


# ----------------------------------------------------------------- L-BFGS


@dataclasses.dataclass(frozen=True)
class LBFGS:
    memory: int = 10
    max_step: float = 0.5  # longest step in theta (a factor e^0.5 on a log-parametrised gain)
    first_step: float = 0.1  # length of the first (steepest-descent) step
    armijo: float = 1e-4
    shrink: float = 0.3
    max_trials: int = 6
    renewals: int = 4  # fresh training batches after converging on one (where the oracle can renew)
    # a fresh batch starts from the curvature pairs of the last (the same cost on other scenarios: a
    # close Hessian); without them each batch starts over from a short steepest-descent step
    renewal_memory: bool = True
    # a step that lowers the cost by at most ftol * max(|f|, |f_new|, 1) counts as none (it is taken):
    # scipy's L-BFGS-B criterion at its default (factr 1e7 times float64's epsilon). Without it a batch
    # whose cost holds a large constant (a dropped scenario's) is lowered by ever smaller accepted steps
    ftol: float = 2.220446049250313e-09
    needs = ("value_and_grad",)

    def init(self, x0, seed: int = 0) -> dict:
        return {"x": np.asarray(x0, dtype=float), "f": None, "g": None, "s": [], "y": [], "batch": 0, "stalled": False}

    def _direction(self, g, s_hist, y_hist):
        if not s_hist:
            return -g * (self.first_step / max(np.linalg.norm(g), 1e-300))
        q = g.copy()
        alphas = []
        for s, y in zip(reversed(s_hist), reversed(y_hist), strict=True):
            a = (s @ q) / (y @ s)
            alphas.append(a)
            q = q - a * y
        s, y = s_hist[-1], y_hist[-1]
        q = q * ((s @ y) / (y @ y))
        for (s, y), a in zip(zip(s_hist, y_hist, strict=True), reversed(alphas), strict=True):
            b = (y @ q) / (y @ s)
            q = q + (a - b) * s
        return -q

    def step(self, state, oracle: Oracle):
        batch = int(state.get("batch", 0))
        if state.get("converged", False):  # nothing left to do: no step, no evaluation
            g = state["g"]
            return state, {"train_cost": state["f"], "grad_norm": float(np.linalg.norm(g)), "accepted": 0,
                           "batch": batch, "trials": 0, "converged": 1}  # fmt: skip
        if oracle.renew is not None:
            oracle.use(batch)  # a resumed run's oracle starts on batch 0
        x, f, g = state["x"], state["f"], state["g"]
        if g is None:
            f, g = oracle.vg(x)
            if not (np.isfinite(f) and np.all(np.isfinite(g))):
                return state, {"train_cost": f, "grad_norm": float("nan"), "accepted": 0}
        d = self._direction(g, state["s"], state["y"])
        slope = g @ d
        if not slope < 0:  # not a descent direction: forget the curvature
            d, slope = -g * (self.first_step / max(np.linalg.norm(g), 1e-300)), -self.first_step * np.linalg.norm(g)
            state = {**state, "s": [], "y": []}
        alpha = min(1.0, self.max_step / max(np.linalg.norm(d), 1e-300))
        cheap = oracle.value is not None
        # the first trial takes the gradient with its value unless the last line
        # search backtracked (then the first trial is likely rejected as well)
        probe = not (cheap and state.get("backtracked", False))
        for trial in range(self.max_trials):
            x_new = x + alpha * d
            if not cheap or (trial == 0 and probe):
                f_new, g_new = oracle.vg(x_new)
                ok = np.isfinite(f_new) and np.all(np.isfinite(g_new))
            else:
                f_new, g_new = oracle.v(x_new), None
                ok = np.isfinite(f_new)
            lower = ok and f_new < f and f_new <= f + self.armijo * alpha * slope  # a step that lowers the cost
            if lower and g_new is None:  # accepted on its value: now its gradient
                f_new, g_new = oracle.vg(x_new)
                lower = np.isfinite(f_new) and np.all(np.isfinite(g_new))
            if lower:
                s, y = x_new - x, g_new - g
                s_hist, y_hist = list(state["s"]), list(state["y"])
                if s @ y > 1e-10 * np.linalg.norm(s) * np.linalg.norm(y):
                    s_hist, y_hist = (s_hist + [s])[-self.memory :], (y_hist + [y])[-self.memory :]
                row = {"train_cost": f_new, "grad_norm": float(np.linalg.norm(g_new)), "accepted": 1, "batch": batch}
                row["trials"] = trial + 1
                small = f - f_new <= self.ftol * max(abs(f), abs(f_new), 1.0)
                row = {**row, "small": self.ftol} if small else row  # the tolerance it met
                if small and state.get("stalled", False):  # the second step in a row that lowers it by nothing
                    return self._leave_batch(x_new, f_new, g_new, s_hist, y_hist, batch, oracle, row)
                new = {"x": x_new, "f": f_new, "g": g_new, "s": s_hist, "y": y_hist, "backtracked": trial > 0}
                if small:  # taken, but counted as no lower cost (the curvature holds: kept for a fresh batch)
                    kept = {"kept_s": list(s_hist), "kept_y": list(y_hist)} if self.renewal_memory else {}
                    return {**new, "batch": batch, "stalled": True, **kept}, row
                return {**new, "batch": batch, "stalled": False}, row
            alpha *= self.shrink
        row = {"train_cost": f, "grad_norm": float(np.linalg.norm(g)), "accepted": 0, "batch": batch}
        row["trials"] = self.max_trials
        if not state.get("stalled", False):
            # no acceptable step: stay, forget the curvature (the next step is a short steepest descent),
            # kept for a fresh batch
            kept = {"kept_s": list(state["s"]), "kept_y": list(state["y"])} if self.renewal_memory else {}
            return {"x": x, "f": f, "g": g, "s": [], "y": [], "batch": batch, "stalled": True, "backtracked": True,
                    **kept}, row  # fmt: skip
        # the second time in a row: converged on this batch
        return self._leave_batch(x, f, g, state.get("kept_s", []), state.get("kept_y", []), batch, oracle, row)

    def _leave_batch(self, x, f, g, s_hist, y_hist, batch, oracle, row):
        """Converged on batch ``batch``: on to the next, from ``x`` and the curvature pairs given
        (where the oracle can renew and renewals are left), else converged."""
        if oracle.renew is not None and batch < self.renewals:
            oracle.use(batch + 1)
            row["renewed"] = batch + 1
            s_hist, y_hist = (s_hist, y_hist) if self.renewal_memory else ([], [])
            return {"x": x, "f": None, "g": None, "s": list(s_hist), "y": list(y_hist), "batch": batch + 1,
                    "stalled": False}, row  # fmt: skip
        row["converged"] = 1
        return {"x": x, "f": f, "g": g, "s": [], "y": [], "batch": batch, "stalled": True, "converged": True}, row

    def incumbent(self, state):
        return state["x"]

    def converged(self, state) -> bool:
        """Whether the run has converged (a resumed one does not step again)."""
        return bool(state.get("converged", False))

    def to_data(self, state) -> dict:
        return dict(state)  # arrays, floats and lists of arrays already

    def from_data(self, data) -> dict:
        out = {**data, "s": list(data["s"]), "y": list(data["y"])}
        out = {**out, **{k: list(data[k]) for k in ("kept_s", "kept_y") if k in data}}
        out = {**out, "batch": int(out.get("batch", 0)), "stalled": bool(out.get("stalled", False))}
        out = {**out, "converged": bool(out.get("converged", False))}
        return {**out, "backtracked": bool(out.get("backtracked", False))}


# ----------------------------------------------------------------- CMA-ES


@dataclasses.dataclass(frozen=True)
class CMAES:
    sigma: float = 0.3
    popsize: int = 16
    needs = ("values",)

    def _strategy(self, x0, seed: int):
        return cma.CMAEvolutionStrategy(
            np.asarray(x0, dtype=float), self.sigma, {"popsize": self.popsize, "seed": seed + 1, "verbose": -9}
        )

    def init(self, x0, seed: int = 0) -> dict:
        x0 = np.asarray(x0, dtype=float)
        return {"es": self._strategy(x0, seed), "x0": x0, "seed": int(seed), "told": []}

    def step(self, state, oracle: Oracle):
        es = state["es"]
        xs = es.ask()
        fs = oracle.pop(np.stack(xs))
        told = [float(v) if np.isfinite(v) else 1e12 for v in fs]
        es.tell(xs, told)
        row = {"train_cost": float(np.nanmin(fs)), "sigma": float(es.sigma), "accepted": 1}
        return {**state, "told": [*state["told"], told]}, row

    def incumbent(self, state):
        return np.asarray(state["es"].mean, dtype=float)

    def to_data(self, state) -> dict:
        """The strategy as data: where it started, its seed and every generation's
        told costs (``cma``'s object is not data); :meth:`from_data` replays them."""
        return {
            "x0": state["x0"],
            "seed": state["seed"],
            "told": [list(t) for t in state["told"]],
            "mean": np.asarray(state["es"].mean, dtype=float),
            "sigma": float(state["es"].sigma),
        }

    def from_data(self, data) -> dict:
        """The strategy rebuilt by replaying its generations: the same samples
        (``cma`` draws them from its seed) told the same costs give the same
        state; checked against the saved mean and step size."""
        es = self._strategy(data["x0"], int(data["seed"]))
        for told in data["told"]:
            es.tell(es.ask(), [float(v) for v in told])
        mean, sigma = np.asarray(es.mean, dtype=float), float(es.sigma)
        if not (np.array_equal(mean, np.asarray(data["mean"], dtype=float)) and sigma == float(data["sigma"])):
            raise ConfigError(
                "the CMA-ES state replayed from the checkpoint differs from the one saved "
                f"(mean off by {float(np.max(np.abs(mean - data['mean']))):.3g}, step size {sigma} against "
                f"{data['sigma']}): another version of the 'cma' package? restart the run"
            )
        return {"es": es, "x0": np.asarray(data["x0"], dtype=float), "seed": int(data["seed"]), "told": data["told"]}


@dataclasses.dataclass(frozen=True)
class CMAESThenLBFGS:
    generations: int = 6
    cmaes: CMAES = CMAES()
    lbfgs: LBFGS = LBFGS()
    needs = ("values", "value_and_grad")

    def init(self, x0, seed: int = 0) -> dict:
        return {"phase": "cmaes", "n": 0, "inner": self.cmaes.init(x0, seed)}

    def step(self, state, oracle: Oracle):
        if state["phase"] == "cmaes":
            inner, row = self.cmaes.step(state["inner"], oracle)
            n = state["n"] + 1
            if n >= self.generations:
                return {"phase": "lbfgs", "n": n, "inner": self.lbfgs.init(self.cmaes.incumbent(inner))}, row
            return {"phase": "cmaes", "n": n, "inner": inner}, row
        inner, row = self.lbfgs.step(state["inner"], oracle)
        return {**state, "inner": inner}, row

    def incumbent(self, state):
        m = self.cmaes if state["phase"] == "cmaes" else self.lbfgs
        return m.incumbent(state["inner"])

    def to_data(self, state) -> dict:
        m = self.cmaes if state["phase"] == "cmaes" else self.lbfgs
        return {**state, "inner": m.to_data(state["inner"])}

    def from_data(self, data) -> dict:
        m = self.cmaes if data["phase"] == "cmaes" else self.lbfgs
        return {**data, "n": int(data["n"]), "inner": m.from_data(data["inner"])}


def get(name: str, **options):
    """A method by name: one of :data:`BATCH_METHODS` with its options, or a
    first-order optax optimiser (:class:`FirstOrder`; its option
    ``optimizer``: the optax transformation, default ``optax.<name>`` at 0.05,
    clipped at 1)."""
    table = {"lbfgs": LBFGS, "cmaes": CMAES, "cmaes-lbfgs": CMAESThenLBFGS}
    if name in table:
        return table[name](**options)
    why = first_order_problem(name)
    if why is not None:
        raise ConfigError(
            f"method must be one of {list(BATCH_METHODS)} or a first-order optax optimiser (adam, sgd, ...), "
            f"got {name!r}: {why}"
        )
    options.setdefault("optimizer", make_optimizer(0.05, optimizer=name, clip_norm=1.0))
    return FirstOrder(**options)
