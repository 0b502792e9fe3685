"""The control-affine system model every benchmark system provides.

A system is ``dx/dt = f(x) + g u(t)``, ``y = h(x)`` with one scalar input.
``f`` and ``h`` are written with array arithmetic and indexing only, so the
same code evaluates numpy arrays and torch tensors (see :func:`stack`): a
learned estimator can differentiate the model with autograd, a filter can use
the analytic Jacobians.
"""

from __future__ import annotations

from abc import ABC, abstractmethod
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, ClassVar

import numpy as np

if TYPE_CHECKING:
    from kkl_bench.protocol.compiled import CompiledModel


def stack(components: list[Any]) -> Any:
    """Stack same-shape arrays on a new last axis, for numpy arrays or torch tensors."""
    first = components[0]
    if isinstance(first, np.ndarray | float | int):
        return np.stack(np.broadcast_arrays(*components), axis=-1)
    import torch  # only reached when the caller passes tensors

    return torch.stack(torch.broadcast_tensors(*components), dim=-1)


def namespace(x: Any) -> Any:
    """The array module of ``x``: ``numpy`` for arrays and numbers, ``torch`` for tensors,
    so that ``f`` and ``h`` written as ``namespace(x).sin(...)`` evaluate both."""
    if isinstance(x, np.ndarray | float | int):
        return np
    import torch  # only reached when the caller passes tensors

    return torch


@dataclass(frozen=True)
class Ring:
    """How a system's states sit on a ring of identical sites (Lorenz-96): what a local
    observer needs (``ring_observer``); a system that is not a ring declares none.

    Attributes
    ----------
    sites: number of sites; site ``s`` holds states ``s k, ..., s k + k - 1`` with
        ``k = n_x / sites`` (site-major order), and its neighbours are ``s - 1`` and
        ``s + 1`` modulo ``sites``.
    output_sites: ``(n_y,)`` the site each output component measures (at most one
        output per site).
    """

    sites: int
    output_sites: tuple[int, ...]

    def __post_init__(self) -> None:
        if len(set(self.output_sites)) != len(self.output_sites):
            raise ValueError(f"a ring site has at most one output, got {self.output_sites}")
        outside = [s for s in self.output_sites if not 0 <= s < self.sites]
        if outside:
            raise ValueError(f"output sites {outside} are not among the {self.sites} sites")


class System(ABC):
    """A control-affine benchmark system.

    Subclasses set the class attributes and implement :meth:`f`,
    :meth:`h` and their Jacobians. All methods are batched over leading axes:
    ``x: (..., n_x)``.

    Attributes
    ----------
    name: registry name, e.g. ``"duffing"``.
    state_names: names of the state components, length ``n_x``.
    g: ``(n_x,)`` input direction.
    x0_low, x0_high: ``(n_x,)`` corners of the box initial states are drawn from.
    n_y: number of measured outputs (default 1).
    ring: the sites the states sit on, if the system is a ring (:class:`Ring`; default
        None). A ring system also implements :meth:`with_sites`.
    """

    name: ClassVar[str]
    state_names: ClassVar[tuple[str, ...]]
    g: ClassVar[np.ndarray]
    x0_low: ClassVar[np.ndarray]
    x0_high: ClassVar[np.ndarray]
    n_y: ClassVar[int] = 1
    ring: ClassVar[Ring | None] = None

    @property
    def n_x(self) -> int:
        """Number of states, ``len(state_names)``."""
        return len(self.state_names)

    @property
    def n_z(self) -> int:
        """KKL latent size ``n_y (2 n_x + 1)``."""
        return self.n_y * (2 * self.n_x + 1)

    @abstractmethod
    def f(self, x):
        """Drift. ``x: (..., n_x)`` -> ``(..., n_x)``."""

    @abstractmethod
    def h(self, x):
        """Output. ``x: (..., n_x)`` -> ``(..., n_y)``."""

    @abstractmethod
    def f_jacobian(self, x: np.ndarray) -> np.ndarray:
        """``df/dx``. ``x: (..., n_x)`` -> ``(..., n_x, n_x)``."""

    @abstractmethod
    def h_jacobian(self, x: np.ndarray) -> np.ndarray:
        """``dh/dx``. ``x: (..., n_x)`` -> ``(..., n_y, n_x)``."""

    def vector_field(self, x, u):
        """``f(x) + g u``. ``x: (..., n_x)``, ``u: (...)`` -> ``(..., n_x)``."""
        if isinstance(x, np.ndarray):
            return self.f(x) + u[..., None] * self.g
        import torch  # only reached when the caller passes tensors

        return self.f(x) + u[..., None] * torch.as_tensor(self.g, dtype=x.dtype, device=x.device)

    def constrain(self, x: np.ndarray) -> np.ndarray:
        """Map a state perturbed by process noise back into the system's domain.

        The identity for most systems; see ``docs/protocol.md`` (erratum E1)
        for the one that needs it. ``x: (..., n_x)`` -> ``(..., n_x)``.
        """
        return x

    def params(self) -> dict[str, float]:
        """The model's named parameters (for provenance)."""
        return {}

    def compiled(self) -> CompiledModel | None:
        """The model as numba functions that sweep over points (``x: (n_x, m)``, the points
        on the last axis; each writes its result into its last argument or in place and
        returns nothing; :class:`kkl_bench.protocol.compiled.CompiledModel` gives each
        one's signature), what the filters' compiled engine runs; None (the default) if the
        system offers none, and the filters then run their reference engine."""
        return None

    def with_sites(self, sites: int) -> System:
        """The same system on a ring of ``sites`` sites (a ring observer trained at one
        size is applied at another); only a ring system implements it."""
        raise TypeError(f"{self.name} is not a ring system (it declares no System.ring)")

    def __repr__(self) -> str:
        params = ", ".join(f"{key}={value:g}" for key, value in self.params().items())
        return f"{type(self).__name__}({params})"


class ReadThrough(System, ABC):
    """Another system's dynamics read through an output of its own: subclasses implement
    :meth:`h` and :meth:`h_jacobian` from ``self.model``'s; everything else (``f``, its
    Jacobian, the constraint, the parameters, the x0 box, any attribute the model
    declares) is ``model``'s."""

    def __init__(self, model: System) -> None:
        self.model = model
        self.name = model.name
        self.state_names = model.state_names
        self.g = model.g
        self.x0_low, self.x0_high = model.x0_low, model.x0_high
        self.n_y = model.n_y
        self.ring = model.ring

    def f(self, x):
        return self.model.f(x)

    def f_jacobian(self, x):
        return self.model.f_jacobian(x)

    def constrain(self, x):
        return self.model.constrain(x)

    def params(self):
        return self.model.params()

    def compiled(self):
        """None: a subclass that reads the output its own way says how to compile it."""
        return None

    def __getattr__(self, name: str):  # anything else the model declares
        if "model" not in self.__dict__:  # being copied or unpickled: not set up yet
            raise AttributeError(name)
        return getattr(self.__dict__["model"], name)


class MeasureOneState(System, ABC):
    """A system whose output is one state component, ``y = x[measured]``."""

    measured: ClassVar[int]

    def h(self, x):
        return x[..., self.measured : self.measured + 1]

    def h_jacobian(self, x: np.ndarray) -> np.ndarray:
        jacobian = np.zeros((*x.shape[:-1], 1, self.n_x))
        jacobian[..., 0, self.measured] = 1.0
        return jacobian
