"""Input validation shared by every public entry point: one place words the errors."""

from __future__ import annotations

import math
import numbers
import operator
from collections.abc import Callable, Sequence
from typing import TypeVar

import numpy as np
import torch
from torch import Tensor

SUPPORTED_DTYPES = (torch.float32, torch.float64)
"""The floating-point dtypes torchsurf computes in. Half precision is refused: its epsilon
(about 1e-3) is above the finite-difference errors the operators are built to, and squares of
small gradients underflow to 0 (NaN normals)."""


T = TypeVar("T")


class MismatchError(TypeError, ValueError):
    """A tensor whose dtype or device differs from the one it is used with.

    Both a ``TypeError`` and a ``ValueError``, so that either ``except`` clause catches it,
    whichever layer (functional, module, surface, bricks, sampling) raised it."""


def _dtype_error(name: str, dtype: object, what: str) -> TypeError:
    return TypeError(
        f"{name} must be {what} torch.float32 or torch.float64 (the dtypes torchsurf "
        f"supports), got {dtype}"
    )


def check_dtype(dtype: object, name: str = "dtype") -> torch.dtype:
    """``dtype``, or the default dtype for ``None``; raise naming ``name`` unless supported."""
    if dtype is None:
        dtype = torch.get_default_dtype()
    if dtype not in SUPPORTED_DTYPES:
        raise _dtype_error(name, dtype, "a floating-point dtype,")
    return dtype


def check_device(device: object, name: str = "device") -> torch.device | None:
    """``None``, or ``torch.device(device)``; raise ``ValueError`` naming ``name`` where torch
    cannot read it (``"gpu"``), has no such device (``"cuda"`` on a CPU build), or it is
    ``"meta"`` (no values to read)."""
    if device is None:
        return None
    try:
        parsed = torch.device(device)
    except (RuntimeError, TypeError) as error:
        raise ValueError(f"{name} must name a torch device ('cpu', 'cuda', 'cuda:0', ...), got "
                         f"{device!r}") from error
    if parsed.type == "meta":
        raise ValueError(f"{name}={device!r} holds no values; torchsurf needs real data: use "
                         "'cpu' or 'cuda'")
    if parsed.type == "cuda" and not torch.cuda.is_available():
        raise ValueError(f"{name}={device!r}: this torch has no CUDA device "
                         "(torch.cuda.is_available() is False); use 'cpu'")
    return parsed


def check_has_data(value: Tensor, name: str) -> Tensor:
    """Raise ``ValueError`` naming ``name`` if ``value`` lives on the meta device.

    Meta tensors have shapes but no values; torchsurf reads values (signs of ``phi``, finiteness
    checks, step bounds) before any work, so it cannot run on them.
    """
    if value.is_meta:
        raise ValueError(
            f"{name} is on the meta device (shape {tuple(value.shape)}, dtype {value.dtype}), "
            "which holds no values; torchsurf needs real data: create it on 'cpu' or 'cuda'"
        )
    return value


def check_tensor(value: object, name: str) -> Tensor:
    """Raise ``TypeError`` naming ``name`` unless ``value`` is a float32 or float64 tensor,
    ``ValueError`` if it is on the meta device (no values)."""
    if not isinstance(value, Tensor):
        raise TypeError(f"{name} must be a torch.Tensor, got {type(value).__name__}")
    check_has_data(value, name)
    if value.dtype not in SUPPORTED_DTYPES:
        raise _dtype_error(name, f"dtype {value.dtype}", "a floating-point tensor of dtype")
    return value


def check_like_first(entry: Tensor, first: Tensor, name: str, first_name: str) -> None:
    """Raise naming ``name`` (``ValueError``; :class:`MismatchError` for a dtype or device) unless
    ``entry`` (``(V_b, C)``, one of a list) has
    the channel count, dtype and device of the list's ``first`` entry, named ``first_name``:
    entries are joined into one batch, which would promote mixed dtypes silently."""
    if (entry.shape[-1], entry.dtype, entry.device) != (first.shape[-1], first.dtype,
                                                        first.device):
        error = ValueError if entry.shape[-1] != first.shape[-1] else MismatchError
        raise error(
            f"{name} has {entry.shape[-1]} channels of {entry.dtype} on {entry.device}, "
            f"{first_name} {first.shape[-1]} of {first.dtype} on {first.device}: every entry "
            "needs the same C, dtype and device"
        )


def check_module_dtype(value: Tensor, name: str, reference: Tensor, owner: str) -> None:
    """Raise :class:`MismatchError` naming ``name`` unless ``value`` has the dtype and device
    of ``reference``, a buffer of the module ``owner`` (its weights would otherwise be cast,
    or the result promoted, silently)."""
    if (value.dtype, value.device) != (reference.dtype, reference.device):
        raise MismatchError(
            f"{name} is {value.dtype} on {value.device} but the {owner} is {reference.dtype} on "
            f"{reference.device}: they must match (convert one, e.g. {owner}.to(...))"
        )


def check_volume(value: object, name: str, channels: int | None = None) -> Tensor:
    """Check that ``value`` is a floating-point volume ``(B, C, D, H, W)``.

    Args:
        value: the tensor to check.
        name: the argument's name, used in the error message.
        channels: the required ``C``, or ``None`` for any.
    """
    volume = check_tensor(value, name)
    if volume.dim() != 5:
        raise ValueError(
            f"{name} must be a volume of shape (B, C, D, H, W), got shape {tuple(volume.shape)}"
        )
    if volume.shape[0] == 0 or volume.shape[1] == 0:
        raise ValueError(
            f"{name} must hold at least one volume and one channel, got shape "
            f"{tuple(volume.shape)} (B = {volume.shape[0]}, C = {volume.shape[1]})"
        )
    if channels is not None and volume.shape[1] != channels:
        raise ValueError(
            f"{name} must have {channels} channel(s), shape (B, {channels}, D, H, W), "
            f"got shape {tuple(volume.shape)}"
        )
    return volume


def check_finite(value: Tensor, name: str) -> Tensor:
    """Raise ``ValueError`` naming ``name`` if ``value`` holds NaN or infinity.

    Not checked while ``torch.compile`` traces: the check reads the data on the host, which
    would break the graph (a traced flow then returns NaN where the eager one raises).
    """
    if torch.compiler.is_compiling():
        return value
    if not bool(torch.isfinite(value).all()):
        raise ValueError(f"{name} must hold finite values only, found NaN or infinity")
    return value


def check_spatial_shape(value: Tensor, name: str, shape: Sequence[int], against: str) -> None:
    """Raise ``ValueError`` unless the last three sizes of ``value`` equal ``shape``."""
    if tuple(value.shape[-3:]) != tuple(shape):
        raise ValueError(
            f"{name} has spatial shape {tuple(value.shape[-3:])} but {against} has "
            f"{tuple(shape)}; they must agree"
        )


def check_batch(value: Tensor, name: str, batch: int, against: str) -> None:
    """Raise ``ValueError`` unless ``value``'s batch size is 1 or equals ``batch``, or vice versa."""
    size = value.shape[0]
    if size != batch and size != 1 and batch != 1:
        raise ValueError(
            f"{name} has batch size {size} but {against} has {batch}; "
            "they must be equal or one of them must be 1"
        )


def check_alike(fields: Sequence[tuple[str, Tensor | None, int | None]]) -> None:
    """Raise naming the argument unless the tensors ``(name, tensor, channels)`` given (a
    ``None`` tensor is left out) are ``(B, channels, ...)`` (any channels for ``None``) on the
    grid of the first, of its dtype and device, their batch sizes equal or 1 (they broadcast):
    ``ValueError`` for a shape, :class:`MismatchError` for a dtype or a device."""
    given = [(name, value, channels) for name, value, channels in fields if value is not None]
    first_name, first, _ = given[0]
    for name, value, channels in given:
        if (value.dim() != first.dim() or value.dim() < 3 or value.shape[2:] != first.shape[2:]
                or channels is not None and value.shape[1] != channels):
            wanted = (f"(B or 1, {'C' if channels is None else channels}, *grid) with at least "
                      f"one grid axis")
            grid = "" if name == first_name else f" on the grid of {first_name} {tuple(first.shape)}"
            raise ValueError(f"{name} must be {wanted}{grid}, got shape {tuple(value.shape)}")
        if value.dtype != first.dtype:
            raise MismatchError(f"{name} is {value.dtype} but {first_name} is {first.dtype}: they "
                            "must match")
        if value.device != first.device:
            raise MismatchError(f"{name} is on {value.device} but {first_name} is on "
                                f"{first.device}: they must be on one device")
    batches = {int(value.shape[0]) for _, value, _ in given} - {1}  # traced sizes are tensors
    if len(batches) > 1:
        names = ", ".join(name for name, _, _ in given)
        raise ValueError(f"the batch sizes of {names} must be equal or 1, got {sorted(batches)}")


def check_choice(value: str, name: str, choices: Sequence[str]) -> str:
    """Raise ``ValueError`` naming ``name`` unless ``value`` is one of ``choices``."""
    if value not in choices:
        raise ValueError(f"{name} must be one of {sorted(choices)}, got {value!r}")
    return value


def as_float(value: object, name: str, expected: str) -> float:
    """A Python float from a real number: Python, numpy, or a 0-d tensor; never a bool.

    Raises ``TypeError`` naming ``name`` and saying ``expected`` for anything else (bools,
    strings, complex numbers, tensors with more than one element).
    """
    if isinstance(value, Tensor):
        if value.dim() == 0 and value.dtype != torch.bool and not value.is_complex():
            return float(check_has_data(value, name).detach())  # the number, read to check it
    elif isinstance(value, numbers.Real) and not isinstance(value, bool):
        return float(value)
    kind = f"a tensor of shape {tuple(value.shape)} and dtype {value.dtype}" if isinstance(
        value, Tensor) else f"a {type(value).__name__}"
    raise TypeError(f"{name} must be {expected}, got {value!r} ({kind})")


def as_real_tensor(value: object, name: str, expected: str) -> Tensor:
    """``value`` (a number, a sequence of numbers, an array or a tensor) as a new default-dtype
    tensor, detached; bools, strings, ``None`` and complex numbers refused with ``TypeError``
    naming ``name`` and saying ``expected``."""
    if isinstance(value, (Tensor, np.ndarray)):
        tensor = value if isinstance(value, Tensor) else torch.as_tensor(value, device="cpu")
        tensor = check_has_data(tensor.detach(), name)
        if tensor.dtype == torch.bool or tensor.is_complex():
            raise TypeError(f"{name} must be {expected}, got a tensor of dtype {tensor.dtype}")
        return tensor.to(torch.get_default_dtype()).clone()
    if isinstance(value, Sequence) and not isinstance(value, str):
        entries = [as_float(v, f"{name}[{i}]", expected) for i, v in enumerate(value)]
        return torch.tensor(entries, dtype=torch.get_default_dtype(), device=_settings_device())
    return torch.tensor(as_float(value, name, expected), dtype=torch.get_default_dtype(),
                        device=_settings_device())


def _settings_device() -> torch.device:
    """Where numbers given as settings become tensors: the default device (``with
    torch.device("cuda")`` puts a layer's parameters there, as ``nn.Linear``'s), the CPU
    when that is ``meta`` (whose tensors hold no values to check)."""
    default = torch.empty(0).device
    return torch.device("cpu") if default.type == "meta" else default


def check_triple(value: object, name: str, check: Callable[[object, str], T]) -> tuple[T, T, T]:
    """Three entries of ``value``, each passed through ``check`` (which names ``name``)."""
    try:
        entries = tuple(value)
    except TypeError:
        entries = ()
    if len(entries) != 3:
        raise ValueError(f"{name} must have three entries, got {value!r}")
    try:
        return tuple(check(entry, f"each entry of {name}") for entry in entries)
    except (TypeError, ValueError) as error:
        raise type(error)(f"{name} = {value!r}: {error}") from error


def check_real(value: object, name: str) -> float:
    """A finite real number (Python, numpy or 0-d tensor) as a float; raise naming ``name``."""
    number = as_float(value, name, "a finite real number")
    if not math.isfinite(number):
        raise ValueError(f"{name} must be a finite real number, got {value!r}")
    return number


def check_nonnegative(value: object, name: str) -> float:
    """A finite real number ``>= 0`` (Python, numpy or 0-d tensor) as a float."""
    number = as_float(value, name, "a finite number >= 0")
    if not (math.isfinite(number) and number >= 0):
        raise ValueError(f"{name} must be a finite number >= 0, got {value!r}")
    return number


def check_positive(value: object, name: str) -> float:
    """A finite real number ``> 0`` (Python, numpy or 0-d tensor) as a float.

    Raises ``TypeError`` for what is not a real number (bools and strings included) and
    ``ValueError`` for zero, negative, NaN or infinite values, both naming ``name``.
    """
    number = as_float(value, name, "a finite positive number")
    if not (math.isfinite(number) and number > 0):
        raise ValueError(f"{name} must be a finite positive number, got {value!r}")
    return number


def check_positive_tensor(value: object, name: str) -> Tensor:
    """Raise naming ``name`` unless ``value`` is a float tensor of finite values ``> 0``.

    The values are not read while ``torch.compile`` traces the caller (a host read would break
    its graph: a per-channel contrast broke a flow's at every step); the eager calls check
    them."""
    tensor = check_tensor(value, name)
    if torch.compiler.is_compiling():
        return tensor
    finite = torch.isfinite(tensor)
    if not bool((finite & (tensor > 0)).all()):
        bad = "NaN or infinity" if not bool(finite.all()) else (
            f"a minimum of {float(tensor.detach().min()):g}")
        raise ValueError(
            f"{name} must hold finite positive values only, got {bad} in a tensor of shape "
            f"{tuple(tensor.shape)}"
        )
    return tensor


def check_flag(value: object, name: str) -> bool:
    """``value`` as a ``bool``: Python or numpy booleans, or a 0-d bool tensor.

    Raises ``TypeError`` naming ``name`` for anything else: ``bool("False")`` is ``True``, so a
    string or a number is refused rather than read by its truth.
    """
    if isinstance(value, (bool, np.bool_)):
        return bool(value)
    if isinstance(value, Tensor) and value.dim() == 0 and value.dtype == torch.bool:
        return bool(value)
    raise TypeError(f"{name} must be True or False, got {value!r}")


def check_generator(value: object, name: str = "generator") -> torch.Generator | None:
    """``value`` if it is a ``torch.Generator`` or ``None``; raises ``TypeError`` naming ``name``
    otherwise (a seed given as a number is the usual mistake)."""
    if value is None or isinstance(value, torch.Generator):
        return value
    raise TypeError(f"{name} must be a torch.Generator or None, got {type(value).__name__} "
                    "(seed one: torch.Generator().manual_seed(seed))")


def check_entry(entry: object, count: int, name: str = "entry") -> int:
    """``entry`` as an ``int`` in ``[0, count)``: Python and numpy integers and 0-d integer
    tensors; ``ValueError`` naming ``name`` for anything else (bools, fractions, out of range)."""
    try:
        index = None if isinstance(entry, (bool, np.bool_)) else operator.index(entry)
    except TypeError:
        index = None
    if index is None or not 0 <= index < count:
        raise ValueError(f"{name} must be an integer in [0, {count}), got {entry}")
    return index


def check_count(value: object, name: str, minimum: int = 1) -> int:
    """A whole number ``>= minimum`` as an ``int``.

    Accepted: Python and numpy integers, integral floats (``4.0``, ``1e6``) and 0-d integer or
    float tensors holding a whole number. Raises ``TypeError`` naming ``name`` for what is not
    a real number (bools, strings, ``None``, complex numbers, tensors with more than one
    element), as :func:`as_float` does, and ``ValueError`` for a fraction, a non-finite value
    or a number below ``minimum``.
    """
    expected = f"a whole number >= {minimum}"
    if isinstance(value, numbers.Integral) and not isinstance(value, (bool, np.bool_)):
        number: float | int = int(value)
    elif (isinstance(value, Tensor) and value.dim() == 0 and value.dtype != torch.bool
          and not value.is_floating_point() and not value.is_complex()):
        number = int(check_has_data(value, name))  # exact: float() rounds from 2^53
    else:
        number = as_float(value, name, expected)
        if not (math.isfinite(number) and number.is_integer()):
            raise ValueError(f"{name} must be {expected}, got {value!r}")
        number = int(number)
    if number < minimum:
        raise ValueError(f"{name} must be {expected}, got {value!r}")
    return number


def check_loaded_shapes(module: torch.nn.Module, state_dict: dict, prefix: str) -> None:
    """Raise ``ValueError`` naming the first tensor of ``module``'s state (its own, its
    children's, their extra states') whose entry in ``state_dict`` has another shape, before
    ``load_state_dict`` writes anything: an adapter whose tables index its surface's nodes would
    otherwise be left half-loaded, the surface another mesh's and the tables its own."""
    for key, current in module.state_dict().items():
        loaded = state_dict.get(prefix + key)
        pairs = ([(key, current, loaded)] if isinstance(current, Tensor) else
                 [(f"{key}[{name!r}]", value, loaded.get(name)) for name, value in current.items()]
                 if isinstance(current, dict) and isinstance(loaded, dict) else [])
        for name, mine, theirs in pairs:
            if (isinstance(mine, Tensor) and isinstance(theirs, Tensor)
                    and mine.shape != theirs.shape):
                raise ValueError(
                    f"{type(module).__name__}: the loaded {name} has shape {tuple(theirs.shape)} "
                    f"where this one's has {tuple(mine.shape)}: the state of another mesh or "
                    "grid (nothing was loaded); build the module of that mesh or grid instead")
