"""One optax step, shared by the optax loops.

The tuner's Adam (``jaxsync.optimize.tuning.tune``) and the benchmark's tuning step
(``jaxsync bench``) update their parameters here (the other methods:
``optimize.methods``): clip, step, and skip a non-finite step (keep the parameters
and the optimiser state). Pure: it runs eagerly or inside ``jax.jit``.
"""

from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import optax


class Update(NamedTuple):
    params: object  # the updated parameters (unchanged when the step was skipped)
    opt_state: object
    grad_norm: jax.Array  # global norm of the gradient, before clipping
    finite: jax.Array  # bool: the value and the gradient were finite and the step was taken


def first_order_problem(name: str) -> str | None:
    """Why ``optax.<name>(learning_rate)`` cannot be the tuner's optimiser, or
    None when it can: a gradient transformation whose ``update`` takes
    ``(updates, state, params)`` alone (optax's lbfgs also needs the value and a
    line search; ``tree_utils`` is not an optimiser). Traced on shapes only
    (``jax.eval_shape``): nothing runs."""
    factory = getattr(optax, name, None) if isinstance(name, str) and not name.startswith("_") else None
    if not callable(factory):
        return "not an optax optimiser"
    try:
        opt = factory(1e-3)
        if not isinstance(opt, optax.GradientTransformation):
            return f"optax.{name}(learning_rate) is not a gradient transformation"
        p = {"x": jax.ShapeDtypeStruct((2,), jnp.float32)}
        jax.eval_shape(lambda p: opt.update(p, opt.init(p), p), p)
    except Exception as err:  # noqa: BLE001  (any failure means: not usable here; the message says which)
        return f"optax.{name} does not step from (updates, state, params) alone ({type(err).__name__}: {err})"
    return None


def make_optimizer(
    learning_rate: float,
    *,
    optimizer: str = "adam",
    schedule: str = "constant",
    iterations: int | None = None,
    clip_norm: float | None = None,
) -> optax.GradientTransformation:
    """An optax optimiser by name, with an optional cosine schedule (to 10 % over
    ``iterations``) and global-norm clipping.

    Example:
      >>> opt = make_optimizer(0.05, schedule="cosine", iterations=60, clip_norm=1.0)
      >>> state = opt.init({"k": jnp.zeros(())})
    """
    lr = optax.cosine_decay_schedule(learning_rate, iterations, alpha=0.1) if schedule == "cosine" else learning_rate
    opt = getattr(optax, optimizer)(lr)
    return opt if clip_norm is None else optax.chain(optax.clip_by_global_norm(clip_norm), opt)


def apply_update(opt: optax.GradientTransformation, params, opt_state, value, grad) -> Update:
    """One optimiser step from ``(value, grad)``, skipped when either is not finite.

    Example:
      >>> opt = optax.adam(0.1)
      >>> p = {"k": jnp.array(1.0)}
      >>> u = apply_update(opt, p, opt.init(p), jnp.array(1.0), {"k": jnp.array(2.0)})
      >>> bool(u.finite), float(u.params["k"]) < 1.0
      (True, True)
    """
    grad_norm = optax.tree.norm(grad)
    finite = jnp.isfinite(value) & jnp.isfinite(grad_norm)
    updates, new_state = opt.update(grad, opt_state, params)
    new_params = optax.apply_updates(params, updates)

    def keep(new, old):
        return jax.tree_util.tree_map(lambda a, b: jnp.where(finite, a, b), new, old)

    return Update(keep(new_params, params), keep(new_state, opt_state), grad_norm, finite)
