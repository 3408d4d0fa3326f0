"""One optimiser step on a loss written as a pure function, compiled: :class:`Update`.

The eager step (:func:`mixedrl.schedule.descend`) builds an autograd graph, clips with
:func:`torch.nn.utils.clip_grad_norm_` and calls ``torch.optim.Adam.step`` once per run. Here the loss is one
function of tensors compiled by :func:`torch.compile` (``fullgraph=True``) into one graph per loss and shape;
its backward is a second graph (AOTAutograd), run by ``torch.autograd.grad``; each run's gradient-norm clip
and Adam step, written out on the optimiser's own state tensors (:func:`adam_step`), are a third.

**The loss** is any function ``loss(params, *tensors) -> Tensor`` that is *pure*: its result depends only on
``params`` (a tuple of tensors in the order of the network's leaves, :attr:`mixedrl.schedule.Descent.leaves`:
one run's parameters, or ``R`` runs' stacked ``(R, ...)`` parameters) and on the ``tensors`` passed at each
call; networks, the task and constants it closes over are read, never changed, and nothing in it draws random
numbers or converts a tensor to a Python number (no ``float(t)``, ``t.item()``, numpy). It returns shape
``()`` for one run or ``(R,)`` (run ``r``'s loss depending on slice ``r`` of the parameters only), or a pair
``(value, aux)`` whose ``aux`` (tensors, detached by the step) the step returns beside the value: what the
caller needs from the loss's forward pass, e.g. the rollout the critic is fitted on. A network the loss only
reads is frozen around the step (:func:`constants`): the compiled backward differentiates every input that
requires a gradient. :func:`network_at` gives the network at ``params`` inside the loss. Algorithm 2's losses
are :func:`mixedrl.pev.critic_loss_at` (eqs. 49-50) and :func:`mixedrl.pim.actor_objective_at` (eqs. 51-52);
the rollout departure's are :func:`mixedrl.departures.rollout.actor_loss_at` (whose ``H``-step rollout is
compiled as one ``scan``: the graph holds one step, not ``H``) and
:func:`~mixedrl.departures.rollout.critic_loss_at`. Any such loss is stepped the same way, by
:meth:`mixedrl.schedule.Descent.minimise` (``key`` names the loss: one compiled :class:`Update` per key;
checks of the arguments belong before the call, outside the loss)::

    def my_loss(params, s, *, task, actor):
        pi = network_at(actor, params)          # the actor at `params`, differentiable
        ...                                     # pure tensor arithmetic
        return per_run_loss                     # shape () or (R,)

    value = engine.actor_descent.minimise(partial(my_loss, task=task, actor=engine.actor), (s,), active,
                                          key="my_loss")

**Modes** (``algorithm.compile``, :data:`MODES`): ``"off"`` (the default) = the eager step; ``"on"`` = the
compiled step; ``"functional"`` = this module's step run eagerly (``"on"`` falls back to it, with a warning,
when compiling fails). The compiled and the functional step give the eager step's numbers to float32
rounding (the Adam scalars are computed in float64 from the step count, as ``torch.optim.Adam`` does, then
rounded to float32; the order of the sums of the gradient norm and of fused kernels may differ in the last
bit).

**Optimiser state**: the step reads and writes each run's ``torch.optim.Adam`` state (``step``, ``exp_avg``,
``exp_avg_sq``, created as Adam creates them when missing); for ``R > 1`` runs each run's state tensors are
rebound to views of one stacked tensor, so the optimisers' ``state_dict`` and checkpoints are those of the
eager step, and an eager step after a compiled one (or a restored checkpoint) continues the same state. The
learning rate, betas, ``eps`` and the gradient clip are read at every call and passed as tensors, so they
never cause a recompilation. Adam with ``amsgrad``, ``maximize``, ``weight_decay`` or several parameter groups
is refused (``ValueError``).

**Cache**: :func:`configure_cache` points inductor's on-disk cache (``TORCHINDUCTOR_CACHE_DIR``) at the
``inductor`` folder of :func:`cache_dir` (``$MIXEDRL_CACHE_DIR``, default ``~/.cache/mixedrl``), and
:func:`allow_in_cache` lets it keep the graphs that hold a ``scan`` or a custom autograd function. Delete it
(:func:`clear_cache`) to start cold; compile times: docs/algorithm2.rst.
"""

from __future__ import annotations

import contextlib
import logging
import os
import shutil
import warnings
from pathlib import Path
from typing import Any, Callable, Hashable, Iterator, Sequence

import torch
import torch.utils._pytree as pytree

from mixedrl.config_tasks import COMPILE_MODES

__all__ = ["MODES", "Update", "Evaluation", "network_at", "adam_step", "split_aux", "constants", "allow_in_cache",
           "cache_dir", "configure_cache", "clear_cache", "check_mode"]

#: The values of ``algorithm.compile``: the eager step (default), the compiled step, this module's step eagerly.
MODES = COMPILE_MODES

#: A loss: ``loss(params, *tensors) -> Tensor`` of shape () (one run) or (R,) (see the module docstring).
Loss = Callable[..., torch.Tensor]


def check_mode(value: Any, name: str = "algorithm.compile") -> str:
    """Return ``value`` if it is one of :data:`MODES`, else a ``ValueError`` naming ``name``."""
    if not isinstance(value, str) or value not in MODES:
        raise ValueError(f"{name}: expected one of {MODES} (the eager step, compiled, or the functional step "
                         f"without compiling), got {value!r}")
    return value


# ----------------------------------------------------------------------------------------------------
# the cache directory
# ----------------------------------------------------------------------------------------------------
def cache_dir() -> Path:
    """The directory of mixedrl's caches: ``$MIXEDRL_CACHE_DIR``, default ``~/.cache/mixedrl``."""
    env = os.environ.get("MIXEDRL_CACHE_DIR")
    return Path(env).expanduser() if env else Path.home() / ".cache" / "mixedrl"


def configure_cache() -> Path:
    """Point torch's inductor cache (``TORCHINDUCTOR_CACHE_DIR``: compiled kernels, the FX graph and
    AOTAutograd caches) at ``cache_dir() / "inductor"`` and return it.

    A ``TORCHINDUCTOR_CACHE_DIR`` the user set is kept unless ``MIXEDRL_CACHE_DIR`` is set too.
    """
    if "TORCHINDUCTOR_CACHE_DIR" in os.environ and "MIXEDRL_CACHE_DIR" not in os.environ:
        return Path(os.environ["TORCHINDUCTOR_CACHE_DIR"])
    path = cache_dir() / "inductor"
    path.mkdir(parents=True, exist_ok=True)
    os.environ["TORCHINDUCTOR_CACHE_DIR"] = str(path)
    return path


def clear_cache() -> None:
    """Delete ``cache_dir() / "inductor"`` (the next compile is cold)."""
    shutil.rmtree(cache_dir() / "inductor", ignore_errors=True)


# ----------------------------------------------------------------------------------------------------
# a network at given parameters
# ----------------------------------------------------------------------------------------------------
def network_at(network: Any, params: Sequence[torch.Tensor]) -> Callable[..., torch.Tensor]:
    """The function of ``network`` with its parameters replaced by ``params`` (in the order of its leaves).

    Parameters
    ----------
    network : StackedNetwork or torch.nn.Module
        ``R`` stacked runs' networks (:meth:`mixedrl.algorithms.batched.StackedNetwork.at`) or one module
        (:func:`torch.func.functional_call`, its parameters in the order of ``named_parameters``; its
        buffers its own).
    params : sequence of torch.Tensor

    Returns
    -------
    callable
        ``x -> network(x)`` at ``params``, differentiable in them.
    """
    if hasattr(network, "at"):
        return network.at(params)
    names = [name for name, _ in network.named_parameters()]
    named = dict(zip(names, params))
    return lambda *x: torch.func.functional_call(network, named, x)


# ----------------------------------------------------------------------------------------------------
# the step
# ----------------------------------------------------------------------------------------------------
def _per_run(x: torch.Tensor, like: torch.Tensor, stacked: bool) -> torch.Tensor:
    """A per-run scalar (R,) broadcast against a (stacked) tensor: (R, 1, ..., 1), or () for one run."""
    return x.reshape((x.shape[0],) + (1,) * (like.ndim - 1)) if stacked else x.reshape(())


def adam_step(stacked: bool, params: Sequence[torch.Tensor], grads: Sequence[torch.Tensor],
              exp_avgs: Sequence[torch.Tensor], exp_avg_sqs: Sequence[torch.Tensor], steps: Sequence[torch.Tensor],
              hyper: torch.Tensor, mask: torch.Tensor | None) -> None:
    """One clipped Adam step per run on the gradients ``grads``, in place on ``params`` and the state.

    Parameters
    ----------
    stacked : bool
        ``params`` are ``R`` runs' stacked ``(R, ...)`` tensors.
    params, grads, exp_avgs, exp_avg_sqs : sequence of torch.Tensor
        The parameters, their gradients and Adam's moments (stacked like them).
    steps : sequence of torch.Tensor
        Adam's step counts, one per parameter: shape (R,) stacked, () for one run (float32).
    hyper : torch.Tensor, shape (R, 5), float64
        Per run ``lr, beta1, beta2, eps, grad_clip``.
    mask : torch.Tensor of bool, shape (R,), or None
        The runs that step (``None``: all).

    Notes
    -----
    The arithmetic of :func:`torch.nn.utils.clip_grad_norm_` (``g * min(clip / (|g| + 1e-6), 1)``, ``|g|``
    the 2-norm of the run's whole gradient) and of ``torch.optim.Adam``'s single-tensor step
    (``m <- lerp(m, g, 1 - beta1)``, ``v <- beta2 v + (1 - beta2) g^2``,
    ``theta <- theta - lr / (1 - beta1^t) m / (sqrt(v) / sqrt(1 - beta2^t) + eps)``).
    """
    lr, beta1, beta2, eps, clip = hyper.unbind(1)
    if stacked:
        norms = torch.stack([torch.linalg.vector_norm(g.reshape(g.shape[0], -1), dim=1) for g in grads])
        norm = torch.linalg.vector_norm(norms, dim=0)
    else:
        norm = torch.linalg.vector_norm(torch.stack([torch.linalg.vector_norm(g) for g in grads]))
    # grad <- grad min(clip / (|grad| + 1e-6), 1)   (clip_grad_norm_, per run)
    coef = torch.clamp(clip.float() / (norm + 1e-6), max=1.0)
    for p, g, m, v, t in zip(params, grads, exp_avgs, exp_avg_sqs, steps):
        g = g * _per_run(coef, g, stacked)
        t_new = t + 1 if mask is None else t + mask.to(t.dtype)
        n = t_new.double()
        # the scalars as Adam computes them in Python (float64), rounded to float32 by its kernels
        step_size = (lr / (1 - beta1 ** n)).float()
        bc2_sqrt = (1 - beta2 ** n).sqrt().float()
        m_new = torch.lerp(m, g, _per_run((1 - beta1).float(), g, stacked))
        v_new = v * _per_run(beta2.float(), g, stacked) + _per_run((1 - beta2).float(), g, stacked) * g * g
        denom = v_new.sqrt() / _per_run(bc2_sqrt, g, stacked) + _per_run(eps.float(), g, stacked)
        p_new = p - _per_run(step_size, g, stacked) * m_new / denom
        if mask is not None:
            keep = _per_run(mask, p, stacked)
            m_new, v_new, p_new = torch.where(keep, m_new, m), torch.where(keep, v_new, v), torch.where(keep, p_new, p)
        m.copy_(m_new)
        v.copy_(v_new)
        p.copy_(p_new)
        t.copy_(t_new)


def split_aux(out: Any) -> tuple[torch.Tensor, Any]:
    """A loss's result as ``(value, aux)``: ``aux`` is ``None`` unless the loss returned ``(value, aux)``."""
    return (out[0], out[1]) if isinstance(out, tuple) else (out, None)


def detached(value: torch.Tensor, aux: Any) -> Any:
    """``value`` detached, or ``(value, aux)`` with every tensor of ``aux`` detached when ``aux`` is not ``None``."""
    if aux is None:
        return value.detach()
    return value.detach(), pytree.tree_map(lambda t: t.detach() if isinstance(t, torch.Tensor) else t, aux)


class _AdamState:
    """The runs' Adam state of one network, stacked (``R > 1``) or the run's own tensors (``R = 1``), bound
    to the optimisers' ``state`` dicts (rebound when an optimiser's tensors were replaced, e.g. by
    ``load_state_dict``)."""

    def __init__(self, descent: Any) -> None:
        self.descent = descent
        self.stacked = len(descent.optimizers) > 1
        self.tensors: dict[str, list[torch.Tensor]] | None = None
        for opt in descent.optimizers:
            if len(opt.param_groups) != 1:
                raise ValueError("optimizer: the compiled step takes one parameter group per optimiser")
            g = opt.param_groups[0]
            if not isinstance(opt, torch.optim.Adam) or g.get("amsgrad") or g.get("maximize") or \
                    g.get("weight_decay", 0) != 0 or g.get("decoupled_weight_decay", False):
                raise ValueError(f"optimizer: the compiled step writes out Adam without amsgrad, maximize or weight "
                                 f"decay; got {type(opt).__name__} with {({k: v for k, v in g.items() if k != 'params'})}")

    def _bound(self) -> bool:
        if self.tensors is None:
            return False
        for r, (opt, params) in enumerate(zip(self.descent.optimizers, self.descent.run_params)):
            for i, p in enumerate(params):
                st = opt.state.get(p)
                if not st or any(st.get(k) is not self._views[k][i][r] for k in ("step", "exp_avg", "exp_avg_sq")):
                    return False
        return True

    def bind(self) -> dict[str, list[torch.Tensor]]:
        """The state tensors (``step``, ``exp_avg``, ``exp_avg_sq``; one per leaf), created as Adam creates
        them when missing and bound to every optimiser's state."""
        if self._bound():
            return self.tensors
        out: dict[str, list[torch.Tensor]] = {"step": [], "exp_avg": [], "exp_avg_sq": []}
        views: dict[str, list[list[torch.Tensor]]] = {k: [] for k in out}
        for i, leaf in enumerate(self.descent.leaves):
            per_run = []
            for opt, params in zip(self.descent.optimizers, self.descent.run_params):
                p = params[i]
                st = opt.state[p]
                if len(st) == 0:  # Adam's lazy initialisation (capturable and fused off: a float32 step on the CPU)
                    st["step"] = torch.tensor(0.0, dtype=torch.float32)
                    st["exp_avg"] = torch.zeros_like(p, memory_format=torch.preserve_format)
                    st["exp_avg_sq"] = torch.zeros_like(p, memory_format=torch.preserve_format)
                per_run.append(st)
            for key in out:
                if self.stacked:
                    joined = torch.stack([st[key].detach() for st in per_run])
                    for r, st in enumerate(per_run):
                        st[key] = joined[r]
                out[key].append(joined if self.stacked else per_run[0][key])
                views[key].append([st[key] for st in per_run])
        self.tensors, self._views = out, views
        return out


class _Compiled:
    """A function run as :func:`torch.compile` made it (``mode="on"``, one graph, ``fullgraph=True``) or
    eagerly (``"functional"``; ``"on"`` falls back to it, with a warning, when compiling fails).

    ``grad``: whether the function runs with gradients enabled (a loss whose backward autograd computes; the
    compiled loss's backward is then a graph of its own, compiled by AOTAutograd).
    """

    def __init__(self, fn: Callable[..., Any], mode: str, grad: bool = False) -> None:
        if check_mode(mode, "mode") == "off":
            raise ValueError(f"mode: 'off' is the eager step, not a {type(self).__name__}")
        self.fn, self.mode, self.grad = fn, mode, grad
        self._fn: Callable[..., Any] | None = None

    def _function(self) -> Callable[..., Any]:
        if self._fn is None:
            if self.mode == "on":
                configure_cache()
                import torch._dynamo  # the compiler's import (seconds): only when something is compiled

                config = torch._dynamo.config
                config.recompile_limit = max(config.recompile_limit, 64)  # one graph per loss, shape and engine
                config.accumulated_recompile_limit = max(config.accumulated_recompile_limit, 1024)
                allow_in_cache()
                logging.getLogger("mixedrl").info(
                    "algorithm.compile = 'on': %s is compiled at its first calls (cold: tens of seconds per graph; "
                    "cached in %s)", _name(self.fn), os.environ.get("TORCHINDUCTOR_CACHE_DIR"))
                self._fn = torch.compile(self.fn, fullgraph=True, dynamic=False)
            else:
                self._fn = self.fn
        return self._fn

    def _apply(self, fn: Callable[..., Any], *args: Any) -> Any:
        """Call ``fn`` (the compiled or the plain function) on ``args``."""
        return fn(*args)

    def _run(self, *args: Any) -> Any:
        with torch.set_grad_enabled(self.grad):
            try:
                return self._apply(self._function(), *args)
            except Exception as exc:  # noqa: BLE001  (a compiler failure: the same function, eagerly)
                if self.mode != "on" or not _is_compile_error(exc):
                    raise
                warnings.warn(f"algorithm.compile = 'on': compiling {_name(self.fn)} failed "
                              f"({type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}); it runs "
                              f"eagerly instead (the same numbers to float32 rounding)", RuntimeWarning, stacklevel=3)
                self.mode, self._fn = "functional", self.fn
                return self._apply(self.fn, *args)


@contextlib.contextmanager
def constants(*networks: Any) -> Iterator[None]:
    """Inside the block the parameters of ``networks`` (modules; anything else is skipped) do not require
    gradients: a loss reads them as constants. The compiled backward (AOTAutograd) computes the gradient of
    every graph input that requires one, so a network a loss only reads is frozen around its step."""
    params = [p for n in networks if isinstance(n, torch.nn.Module) for p in n.parameters() if p.requires_grad]
    for p in params:
        p.requires_grad_(False)
    try:
        yield
    finally:
        for p in params:
            p.requires_grad_(True)


#: The scan of :func:`mixedrl.departures.rollout.rollout` (``torch._higher_order_ops.scan``) as the inductor
#: and AOTAutograd caches name it.
SCAN = "torch.ops.higher_order.scan"


def allow_in_cache() -> None:
    """Let the on-disk caches keep graphs that hold a ``scan`` (the rollout) or a custom
    ``torch.autograd.Function`` (the inward-clipped actor, :class:`mixedrl.networks.ClippedActor`).

    Torch leaves both out of its caches unless told otherwise, and every process would lower such a graph
    again (about 15 s for the double lane change's default). The cache key holds the graph with the scan's
    body and the function's backward (another constant in either misses: ``tests/test_compiled.py``); the
    torch version, part of every key, guards the operators' own code.
    """
    import torch._functorch.config as functorch
    import torch._inductor.config as inductor

    inductor.unsafe_marked_cacheable_functions.setdefault(SCAN, torch.__version__)
    functorch.autograd_cache_allow_custom_autograd_functions = True


def _name(fn: Any) -> str:
    """A function's name for messages (a ``functools.partial``'s function's)."""
    return getattr(getattr(fn, "func", fn), "__name__", "a step")


class Update(_Compiled):
    """The clipped Adam step of each run of one network on a pure ``loss``: the loss compiled (``mode="on"``)
    or run eagerly (``"functional"``), its gradient by autograd, then :func:`adam_step` (compiled likewise).

    Parameters
    ----------
    loss : callable
        ``loss(params, *tensors)`` (module docstring): the value, or ``(value, aux)``.
    descent : mixedrl.schedule.Descent
        The network's leaves, each run's parameters, optimiser and gradient clip.
    mode : {"on", "functional"}

    Notes
    -----
    Call it as ``update(*tensors, active=None)``; it returns the loss before the step (shape () or (R,),
    detached), or ``(value, aux)`` with ``aux`` detached when the loss returns an ``aux``. Random draws belong
    outside (before the call, in their order): the step draws nothing.
    """

    def __init__(self, loss: Loss, descent: Any, mode: str = "on") -> None:
        super().__init__(loss, mode, grad=True)
        self.descent = descent
        self.state = _AdamState(descent)
        self.stacked = self.state.stacked
        self.adam = _Compiled(adam_step, mode)

    def _apply(self, fn: Callable[..., Any], leaves: list[torch.Tensor], *tensors: torch.Tensor) -> Any:
        """The loss at the leaves and its gradient (a backward the compiler failed on is retried eagerly)."""
        value, aux = split_aux(fn(tuple(leaves), *tensors))
        grads = torch.autograd.grad(value if value.ndim == 0 else value.sum(), leaves)
        return value, aux, grads

    def hyper(self) -> torch.Tensor:
        """Per run ``lr, beta1, beta2, eps, grad_clip`` (float64, (R, 5)), read now (the schedule sets the rates)."""
        rows = []
        for opt, clip in zip(self.descent.optimizers, self.descent.grad_clips):
            g = opt.param_groups[0]
            rows.append([float(g["lr"]), float(g["betas"][0]), float(g["betas"][1]), float(g["eps"]), float(clip)])
        return torch.tensor(rows, dtype=torch.float64)

    def __call__(self, *tensors: torch.Tensor, active: Sequence[int] | None = None) -> Any:
        runs = len(self.descent.optimizers)
        mask = None
        if active is not None and list(active) != list(range(runs)):
            if not self.stacked:
                raise ValueError(f"active: one run, got {list(active)}")
            mask = torch.zeros(runs, dtype=torch.bool)
            mask[list(active)] = True
        st = self.state.bind()
        leaves = list(self.descent.leaves)
        value, aux, grads = self._run(leaves, *tensors)
        self.adam._run(self.stacked, leaves, list(grads), st["exp_avg"], st["exp_avg_sq"], st["step"], self.hyper(),
                       mask)
        return detached(value, aux)


class Evaluation(_Compiled):
    """A pure function of tensors evaluated without gradient (e.g. the MVC's values of ``h``,
    :func:`mixedrl.algorithms.algorithm2.mvc_values`): ``fn`` itself for ``mode="off"``, else compiled
    (``"on"``) or :class:`_Compiled`'s eager fallback (``"functional"``).

    Parameters
    ----------
    fn : callable
        ``fn(*tensors)``, pure (the module docstring's rules for a loss).
    mode : {"off", "on", "functional"}
    """

    def __init__(self, fn: Callable[..., Any], mode: str = "on") -> None:
        self.off = check_mode(mode, "mode") == "off"
        super().__init__(fn, "functional" if self.off else mode)

    def __call__(self, *tensors: torch.Tensor) -> Any:
        if self.off:
            with torch.no_grad():
                return self.fn(*tensors)
        return self._run(*tensors)


def _is_compile_error(exc: BaseException) -> bool:
    """An error of the compiler stack (dynamo, inductor, a missing C compiler), not of the loss."""
    mod = type(exc).__module__ or ""
    return mod.startswith(("torch._dynamo", "torch._inductor", "torch._functorch")) or \
        isinstance(exc, (OSError, ImportError))


def minimise(descent: Any, loss: Loss, tensors: Sequence[torch.Tensor], active: Sequence[int] | None = None,
             key: Hashable = None) -> Any:
    """One step of each (active) run of ``descent`` on ``loss(params, *tensors)`` in the descent's mode
    (:meth:`mixedrl.schedule.Descent.minimise`): the loss before the step, detached, or ``(value, aux)``."""
    if descent.mode == "off":
        value, aux = split_aux(loss(tuple(descent.leaves), *tensors))
        descent(value, active)
        return detached(value, aux)
    key = loss if key is None else key
    update = descent.updates.get(key)
    if update is None:
        update = descent.updates[key] = Update(loss, descent, descent.mode)
    return update(*tensors, active=active)
