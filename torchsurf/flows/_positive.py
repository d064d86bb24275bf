"""Positive flow parameters (times, diffusivities, contrasts), optionally learnable.

A learnable value is stored as an unconstrained ``nn.Parameter`` ``raw`` and read as
``softplus(raw) + floor``, ``floor`` :data:`FLOOR` times the smallest initial entry, so that an
optimiser can never make it zero or negative (softplus alone underflows to exactly 0 for
``raw`` below about -100 in float32); a fixed value stays a Python float (exact, no round trip
through the parametrisation).

What sets a flow's steps is :meth:`Positive.maximum`, a Python float. It reads no tensor for a
fixed value (kept on the host), nor for a learnable one given a ``bound`` (the value is clamped
to it and the bound is the maximum), so that ``torch.compile`` traces a flow's forward whole;
only a learnable value without a bound is read from its parameter (a graph break).
"""

from __future__ import annotations

import math

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

from .._checks import MismatchError, as_real_tensor, check_flag, check_positive
from .._precision import apply_keeping_dtype

FLOOR = 1e-12
"""The smallest value a learnable parameter can take, relative to its smallest initial entry."""


class HostValues:
    """The entries of a small fixed tensor as host floats, read again at every call outside
    ``torch.compile`` (a few values: microseconds), so that a tensor changed in any way, in
    place, replaced, or through ``.data`` (which leaves no trace in ``_version``), is seen;
    under ``torch.compile`` the entries read last are used (a host read would break its graph),
    and the compiled code is specialised on them: their owners read them again in
    ``load_state_dict`` (a checkpoint's values then recompile), but values edited in place
    between compiled calls are not seen until an eager call reads them.

    Args:
        name: the tensor's name in errors.
        tensor: its first value, read now.
        shape: the shape it must keep (a replacement is checked too), or ``None``.
    """

    def __init__(self, name: str, tensor: Tensor, shape: tuple[int, ...] | None = None) -> None:
        self.name = name
        self.shape = shape
        self._entries: tuple[float, ...] = ()
        self.entries_of(tensor)

    def entries_of(self, tensor: Tensor) -> tuple[float, ...]:
        """The entries of ``tensor`` (the one watched), flattened; raises ``ValueError`` naming
        it if it was changed to hold a value that is not finite and positive, or to another
        shape."""
        if not torch.compiler.is_compiling():
            self._entries = self.check(tensor)
        return self._entries

    def of(self, tensor: Tensor) -> float:
        """The largest entry of ``tensor`` (see :meth:`entries_of`)."""
        return max(self.entries_of(tensor))

    def check(self, tensor: Tensor) -> tuple[float, ...]:
        """The entries of ``tensor``, flattened, which must be finite and positive (of
        ``shape``); raises ``ValueError`` naming it otherwise. Keeps nothing."""
        if self.shape is not None and tuple(tensor.shape) != self.shape:
            raise ValueError(f"{self.name} must have shape {self.shape}, got "
                             f"{tuple(tensor.shape)}")
        entries = tuple(float(entry) for entry in tensor.detach().reshape(-1).tolist())
        if not entries or not all(math.isfinite(entry) and entry > 0 for entry in entries):
            raise ValueError(f"{self.name} must hold finite positive values, got "
                             f"{tensor.tolist()!r}")
        return entries

    def check_loaded(self, state_dict: dict, key: str) -> None:
        """Refuse ``state_dict[key]``, if present, before ``load_state_dict`` writes this
        module's values (a failed load would otherwise leave it holding the refused ones),
        naming the key: a model holds several flows."""
        value = state_dict.get(key)
        if isinstance(value, Tensor):
            try:
                self.check(value)
            except ValueError as error:
                raise ValueError(f"loading {key!r}: {error}") from None

    def __setstate__(self, state: dict) -> None:
        state.setdefault("_entries", ())  # a HostMaximum pickled before 2026-12-07
        self.__dict__.update(state)


HostMaximum = HostValues
"""The former name (modules pickled before 2026-12-07 name it)."""


def check_learned_values(module: nn.Module, data: Tensor, data_name: str, owner: str) -> None:
    """:meth:`Positive.check_learned_like` for every :class:`Positive` value in ``module``."""
    for value in module.modules():
        if isinstance(value, Positive):
            value.check_learned_like(data, data_name, owner)


def _reread_entries(module: Positive, _: object) -> None:
    """After ``load_state_dict``: the loaded values, read on the host (see :class:`HostValues`)."""
    module._entries.entries_of(module.values)


_reread_largest = _reread_entries  # the hook's former name, in modules pickled before


def raw_within(value: Tensor, floor: float, bound: float | None) -> Tensor:
    """The raw parameter ``x`` with ``softplus(x) + floor == value``, stepped down where the
    round trip lands above ``bound``: ``torch.clamp(max=bound)`` passes no gradient there, and
    a value started at its bound (accepted within the dtype's rounding) would never move."""
    raw = _inverse_softplus(value - floor)
    if bound is None:
        return raw
    for _ in range(64):
        above = F.softplus(raw) + floor > bound
        if not bool(above.any()):
            break
        raw = torch.where(above, torch.nextafter(raw, torch.full_like(raw, -math.inf)), raw)
    return raw


def _inverse_softplus(value: Tensor) -> Tensor:
    """``x`` with ``softplus(x) == value`` for ``value > 0`` (stable for large values)."""
    return value + torch.log(-torch.expm1(-value))


def range_note(value: object, tensor: Tensor) -> str:
    """``""``, or why ``value``, whose entries are all finite and > 0, is not in ``tensor``
    (``value`` in ``tensor``'s dtype): an entry rounded to 0 or overflowed to infinity."""
    try:
        exact = torch.as_tensor(value, dtype=torch.float64, device=tensor.device)
    except (TypeError, ValueError, RuntimeError):
        return ""
    if exact.shape != tensor.shape or not bool((torch.isfinite(exact) & (exact > 0)).all()):
        return ""
    limits = torch.finfo(tensor.dtype)
    if bool((tensor == 0).any()):
        return (f", which rounds to 0 in {tensor.dtype} (its smallest positive normal value is "
                f"{limits.tiny:.3g})")
    if bool(torch.isinf(tensor).any()):
        return (f", which overflows to infinity in {tensor.dtype} (its largest finite value is "
                f"{limits.max:.3g})")
    return ""


class Positive(nn.Module):
    """A positive number or per-channel vector ``(C,)``, fixed or learnable through softplus.

    Args:
        value: the initial value: a number (Python, numpy or a 0-d tensor), or a sequence,
            array or tensor of shape ``(C,)``, all finite and > 0; never a bool or a string.
        name: the argument's name, used in error messages.
        learnable: register ``softplus^-1(value - floor)`` as an ``nn.Parameter``.
        bound: for a learnable value, its largest value: :meth:`value` is clamped to it (its
            gradient is zero beyond) and :meth:`maximum` returns it without reading the
            parameter. ``bound_name`` names it in errors.
        vector: whether a vector ``(C,)`` is accepted (else a single number only).

    Raises:
        TypeError: ``value`` is not made of real numbers (bools, strings).
        ValueError: it is a tensor that requires grad (its gradient would be lost), has more
            than one dimension (any, without ``vector``), or an entry that is not finite and
            > 0 in the default dtype;
            ``bound`` is given for a fixed value, or is below an entry of ``value``.
    """

    def __init__(self, value: float | Tensor, name: str, learnable: bool = False,
                 bound: float | None = None, bound_name: str = "bound",
                 vector: bool = True) -> None:
        super().__init__()
        self.name = name
        if isinstance(value, Tensor) and value.requires_grad:
            raise ValueError(
                f"{name} is a tensor that requires grad: a flow takes its {name} as a setting and "
                f"would drop that gradient; use learn_{name}=True (the flow then owns the "
                f"parameter) or pass {name}.detach()"
            )
        expected = ("a finite positive number or a vector (C,) of them" if vector
                    else "a single finite positive number")
        tensor = as_real_tensor(value, name, expected)
        self.learnable = check_flag(learnable, "learnable")
        if (not self.learnable and isinstance(value, (Tensor, np.ndarray))
                and value.dtype in (torch.float64, np.float64)):
            # a fixed float64 tensor or array kept, and checked, unrounded (a list takes the
            # default dtype, as torch.tensor gives it)
            tensor = (value if isinstance(value, Tensor) else torch.as_tensor(value, device="cpu")
                      ).detach().to(torch.float64).clone()
        valid = torch.isfinite(tensor) & (tensor > 0)
        if (tensor.dim() > int(vector) or tensor.numel() == 0 or not bool(valid.all())):
            raise ValueError(f"{name} must be {expected}, got {value!r}"
                             f"{range_note(value, tensor)}")
        self.bound = None if bound is None else check_positive(bound, bound_name)
        if self.bound is not None and not self.learnable:
            raise ValueError(f"{bound_name} bounds a learnable {name}; {name} is fixed here")
        # within the rounding of the stored dtype: float32(0.1) > 0.1, and a time at its bound
        # is what docs/learning.md advises for compiling (the clamp then gives the bound)
        if (self.bound is not None
                and float(tensor.max()) > self.bound * (1 + torch.finfo(tensor.dtype).eps)):
            raise ValueError(
                f"{bound_name}={self.bound:g} is below the initial {name} {value!r}; it must be "
                "at least as large"
            )
        self.fixed: float | Tensor | None = None
        self.floor = max(FLOOR * float(tensor.min()), torch.finfo(tensor.dtype).tiny)
        if self.learnable:
            self.raw = nn.Parameter(raw_within(tensor.clone(), self.floor, self.bound))
        elif tensor.dim() == 0:
            self.fixed = check_positive(value, name)
        else:
            self.register_buffer("values", tensor.detach().clone())
            self._entries = HostValues(name, self.values)
            self.register_load_state_dict_post_hook(_reread_entries)

    @property
    def channels(self) -> int | None:
        """``C`` for a per-channel value, ``None`` for a single number."""
        value = self.raw if self.learnable else (None if self.fixed is not None else self.values)
        return None if value is None or value.dim() == 0 else value.shape[0]

    def value(self) -> float | Tensor:
        """The positive value: a float, or a tensor ``()`` / ``(C,)`` in the graph of ``raw``
        (clamped to ``bound`` when one is given)."""
        if self.learnable:
            value = F.softplus(self.raw) + self.floor
            return value if self.bound is None else torch.clamp(value, max=self.bound)
        return self.fixed if self.fixed is not None else self.values

    def maximum(self) -> float:
        """The largest entry, as a float (for step-size bounds); raises if it is not finite.

        Read from the parameter only for a learnable value without ``bound`` (a host read: a
        graph break under ``torch.compile``); a fixed value's is kept on the host, a bound is
        returned as it is. A learnable value can only stop being finite through its raw
        parameter (an optimiser step that went NaN or infinite); the error names the user's
        parameter. Fixed values changed in place or replaced are read again.
        """
        if not self.learnable:  # a single fixed number exactly as given, not rounded
            return self.fixed if self.fixed is not None else self._entries.of(self.values)
        if self.bound is not None:
            return self.bound
        largest = float(self.value().detach().max())
        if not math.isfinite(largest):  # max propagates NaN
            raise ValueError(
                f"{self.name} is no longer finite: its learnable parameter holds "
                f"{self.raw.detach().tolist()!r} (raw, before softplus); an optimiser step "
                "diverged"
            )
        return largest

    def fixed_entries(self) -> tuple[float, ...] | None:
        """A fixed value's entries as host floats, ``(value,)`` for a single number; ``None``
        for a learnable value. Read again at every call as is, the entries read last under
        ``torch.compile`` (:class:`HostValues`)."""
        if self.learnable:
            return None
        return (self.fixed,) if self.fixed is not None else self._entries.entries_of(self.values)

    def values_require_grad(self) -> bool:
        """A fixed per-channel value whose tensor requires grad while autograd records: one
        swapped in by ``torch.func.functional_call``, whose gradient the flow must deliver."""
        values = None if self.learnable or self.fixed is not None else self.values
        return isinstance(values, Tensor) and values.requires_grad and torch.is_grad_enabled()

    def share_of_bound(self) -> float:
        """For a learnable value with ``bound``: its largest entry over the bound, in
        ``(0, 1]``, read on the host (the steps are planned for the bound; what they span in
        time is this share of it). 1 for other values, for a value that is not finite (other
        checks name it), and while ``torch.compile`` traces (no host read)."""
        if not self.learnable or self.bound is None or torch.compiler.is_compiling():
            return 1.0
        largest = float(self.value().detach().max())
        return largest / self.bound if math.isfinite(largest) and largest > 0 else 1.0

    def check_learned_like(self, data: Tensor, data_name: str, owner: str) -> None:
        """Raise :class:`~torchsurf.MismatchError` naming ``data_name`` if this value is learnable
        and its parameter's dtype or device is not ``data``'s: a learned parameter follows the
        module (``owner.to(...)``) as PyTorch's layers' weights do, rather than being cast at
        every call (fixed values are settings, cast to the data's dtype)."""
        raw = getattr(self, "raw", None) if self.learnable else None
        if isinstance(raw, Tensor) and (raw.dtype, raw.device) != (data.dtype, data.device):
            raise MismatchError(
                f"{data_name} is {data.dtype} on {data.device} but the {owner}'s learned "
                f"{self.name} is {raw.dtype} on {raw.device}: they must match (move the module, "
                f"e.g. flow.to({data.dtype}), or the data)")

    def volume(self, like: Tensor) -> float | Tensor:
        """The value shaped to broadcast over a volume ``(B, C, D, H, W)`` like ``like``."""
        value = self.value()
        if isinstance(value, float):
            return value
        if value.dim() == 1 and value.shape[0] not in (1, like.shape[1]):
            raise ValueError(
                f"{self.name} has {value.shape[0]} entries but the data has {like.shape[1]} "
                "channels; give one value or one per channel"
            )
        value = value.to(dtype=like.dtype, device=like.device)
        return value.view(1, -1, 1, 1, 1) if value.dim() == 1 else value

    def _apply(self, fn, recurse=True):  # noqa: ANN001, ANN202
        return apply_keeping_dtype(self, ("values",), lambda: super(Positive, self)._apply(
            fn, recurse))

    def __setstate__(self, state: dict) -> None:
        if "_largest" in state and "_entries" not in state:  # pickled before 2026-12-07
            state["_entries"] = state.pop("_largest")
        super().__setstate__(state)

    def _load_from_state_dict(self, state_dict: dict, prefix: str, *args: object,
                              **kwargs: object) -> None:
        if not self.learnable and self.fixed is None:
            self._entries.check_loaded(state_dict, prefix + "values")
        super()._load_from_state_dict(state_dict, prefix, *args, **kwargs)

    def extra_repr(self) -> str:
        bound = "" if self.bound is None else f", bound={self.bound:g}"
        value = self.value()
        values = torch.as_tensor(value).detach().flatten()
        shown = (f"{float(values[0]):g}" if values.numel() == 1
                 else "[" + ", ".join(f"{float(v):g}" for v in values[:4])
                 + (", ...]" if values.numel() > 4 else "]"))
        return f"{self.name}={shown}, learnable={self.learnable}{bound}"


class ChannelOf(Positive):
    """Entries ``indices`` of a per-channel :class:`Positive` ``whole`` that is learnable, or
    fixed with values that require grad (swapped in by ``torch.func.functional_call``), a
    vector ``(len(indices),)`` in the graph of those values: what a flow that runs those
    channels apart from the others reads, so that its steps and re-extensions follow their
    values (and the gradient reaches each entry through its own channel). Holds no parameter
    of its own; ``bound`` is ``whole``'s."""

    def __init__(self, whole: Positive, indices: list[int]) -> None:
        nn.Module.__init__(self)
        if not (whole.learnable or whole.values_require_grad()) or whole.channels is None:
            raise ValueError("ChannelOf takes a per-channel value, learnable or with values "
                             f"that require grad, got {whole!r}")
        self.whole = whole
        self.indices = list(indices)
        self.name = whole.name
        self.learnable = True
        self.bound = whole.bound
        self.fixed = None
        self.floor = whole.floor

    @property
    def channels(self) -> int | None:
        """The number of channels taken."""
        return len(self.indices)

    def value(self) -> Tensor:
        """The entries ``(len(indices),)``, in the graph of ``whole``'s parameter."""
        value = self.whole.value()
        return value[self.indices[0]:self.indices[0] + 1] if len(self.indices) == 1 \
            else value[self.indices]

    def maximum(self) -> float:
        """The bound, or the largest entry read on the host (``whole`` names its parameter in
        the error if an entry is no longer finite)."""
        if self.bound is not None:
            return self.bound
        self.whole.maximum()
        return float(self.value().detach().max())
