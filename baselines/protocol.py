"""The plug-in protocol of the interpolation benchmark: what a guide-to-dense method implements,
what it is given, and how it is named on the command line.

A method is an :class:`Interpolator`:

- ``fit(train, guides, *, valid=None) -> self``: ``train`` is a
  :class:`~ams_torch.apps.data.HairSequenceDataset` of the train split, opened with
  ``guides=G`` so that every item is a *sample* (below) plus the dense target ``positions``;
  ``guides`` is the (G,) long tensor of guide strand indices; ``valid`` (optional keyword) the
  valid split in the same form, or None. Methods that learn nothing return ``self`` at once.
- ``predict(sample) -> (T, S, N, 3)``: dense positions, metres, world frame, for every frame of
  the sample.
- Optional causal streaming: ``reset(sample)`` with the sample's static part, then
  ``step(frame) -> (S, N, 3)`` once per frame, where ``frame`` holds one frame's
  ``guide_positions`` (G, N, 3), ``rotation`` (3, 3), ``translation`` (3,) and
  ``collider_poses`` (one :class:`~ams_torch.Pose` per collider). ``causal = True`` says the
  method implements them; :func:`stream` runs one.

A *sample* is a dict (tensors on the benchmark's device, float32 unless said):

====================  ========================  ==================================================
key                   shape                     meaning
====================  ========================  ==================================================
guide_positions       (T, G, N, 3) m            the guide strands, world frame: simulated alone
                                                (the default) or the dense run's copies
rotations             (T, 3, 3)                 head rotation at the end of each frame
translations          (T, 3) m                  head translation at the end of each frame
rest_positions        (S, N, 3) m               the dense groom's rest shape, head frame
guide_index           (G,) long                 which dense strands the guides are
num_pinned            (S,) long                 particles from the root that follow the head
colliders             list of C colliders       ams_torch colliders in their own frames; the head
                                                (``sample["head_collider"]`` is its index, or -1)
                                                first when it collides
collider_poses        list of C :class:`Pose`   each collider's world pose per frame, batch (T,)
dt                    float, s                  frame length
sequence, start       int                       the sequence index and the window's first frame
====================  ========================  ==================================================

A method is named by a built-in name (:data:`BUILTINS`, filled by :mod:`baselines.methods`), by
``package.module:factory`` (a callable returning an Interpolator), or by the name of an entry
point in the group ``ams_torch.interpolators`` of an installed package. The factory is called
with the keywords of the benchmark's context that its signature takes (``device``: a
``torch.device``; ``checkpoint``: a file path where a learned method caches its trained
model, keyed by dataset, method and G: when that file exists the method loads it and is ready
to predict without ``fit``; ``fit`` retrains only when it is absent) and with the user's options (``--option NAME.KEY=VALUE``).
"""
from __future__ import annotations

import importlib
import re
import inspect
from abc import ABC, abstractmethod
from typing import Callable, Dict, Optional

import torch

__all__ = ["Interpolator", "BUILTINS", "ENTRY_POINT_GROUP", "register", "resolve_method", "stream",
           "check_prediction", "SAMPLE_KEYS", "MethodError", "NotApplicable", "safe_name", "frame_of", "describe"]

ENTRY_POINT_GROUP = "ams_torch.interpolators"
#: the keys every sample holds (see the module docstring)
SAMPLE_KEYS = ("guide_positions", "rotations", "translations", "rest_positions", "guide_index", "num_pinned",
               "colliders", "collider_poses", "head_collider", "dt", "sequence", "start")
#: built-in method name -> factory (filled by :mod:`baselines.methods` with :func:`register`)
BUILTINS: Dict[str, Callable[..., "Interpolator"]] = {}


class MethodError(ValueError):
    """A method cannot be resolved or returned something that is not a dense prediction."""


class NotApplicable(MethodError):
    """Raised by ``predict`` when the method does not apply to a sample by design (e.g. a model
    bound to the groom it was trained on, given a held-out groom): the benchmark records the
    sequence as not applicable, with the reason, instead of failing."""


class Interpolator(ABC):
    """Base class of guide-to-dense methods (see the module docstring for the protocol).

    Attributes: ``name`` (shown in the leaderboard), ``causal`` (implements ``reset``/``step``),
    ``learned`` (``fit`` trains something).
    """

    name: str = "interpolator"
    causal: bool = False
    learned: bool = False

    def fit(self, train, guides: torch.Tensor, *, valid=None) -> "Interpolator":
        """Learn from the train split (nothing by default). Returns self."""
        return self

    @abstractmethod
    def predict(self, sample: dict) -> torch.Tensor:
        """Dense positions (T, S, N, 3) m, world frame, for every frame of ``sample``."""

    def reset(self, sample: dict) -> None:
        """Start a causal stream on ``sample``'s static part (``causal`` methods)."""
        raise MethodError(f"method {self.name!r} is not causal: it has no reset/step (use predict)")

    def step(self, frame: dict) -> torch.Tensor:
        """One frame of a causal stream → (S, N, 3) m (``causal`` methods)."""
        raise MethodError(f"method {self.name!r} is not causal: it has no reset/step (use predict)")


def register(name: str):
    """Decorator: make ``factory`` the built-in method ``name``."""
    def deco(factory):
        BUILTINS[name] = factory
        return factory
    return deco


def _call_factory(factory: Callable, where: str, context: dict, options: dict) -> Interpolator:
    try:
        sig = inspect.signature(factory)
        takes_all = any(p.kind == p.VAR_KEYWORD for p in sig.parameters.values())
        names = set(sig.parameters)
    except (TypeError, ValueError):  # a builtin or C callable: no signature to read
        takes_all, names = False, set()
    kwargs = {k: v for k, v in context.items() if takes_all or k in names}
    unknown = [k for k in options if not takes_all and k not in names]
    if unknown:
        raise MethodError(f"method {where}: its factory takes no option(s) {unknown} (it takes {sorted(names)})")
    method = factory(**kwargs, **options)
    if not isinstance(method, Interpolator) and not (callable(getattr(method, "predict", None))
                                                     and callable(getattr(method, "fit", None))):
        raise MethodError(f"method {where}: the factory returned {type(method).__name__}, which has no fit/predict "
                          f"(subclass baselines.Interpolator)")
    if not getattr(method, "name", None) or getattr(method, "name") == Interpolator.name:
        try:
            method.name = where
        except AttributeError:
            pass
    return method


def resolve_method(spec: str, context: Optional[dict] = None, **options) -> Interpolator:
    """The Interpolator named ``spec``: a built-in name, ``package.module:factory``, or an entry
    point of the group ``ams_torch.interpolators``. ``context`` (what the benchmark offers every
    method, e.g. ``device``, ``checkpoint``) is passed to the factory for the keywords its
    signature takes; ``options`` (the user's, e.g. ``steps``) must all be taken. Raises
    :class:`MethodError` naming the problem."""
    context = context or {}
    from baselines import methods  # noqa: F401  (fills BUILTINS)

    spec = spec.strip()
    if spec in BUILTINS:
        return _call_factory(BUILTINS[spec], spec, context, options)
    if ":" in spec:
        module, _, attr = spec.partition(":")
        try:
            mod = importlib.import_module(module)
        except ImportError as err:
            raise MethodError(f"method {spec!r}: cannot import module {module!r} ({err})") from None
        factory = mod
        for part in attr.split("."):
            factory = getattr(factory, part, None)
            if factory is None:
                raise MethodError(f"method {spec!r}: module {module!r} has no attribute {attr!r}")
        if not callable(factory):
            raise MethodError(f"method {spec!r}: {attr!r} is not callable")
        return _call_factory(factory, spec, context, options)
    from importlib.metadata import entry_points

    for ep in entry_points(group=ENTRY_POINT_GROUP):
        if ep.name == spec:
            return _call_factory(ep.load(), spec, context, options)
    known = sorted(BUILTINS) + sorted(ep.name for ep in entry_points(group=ENTRY_POINT_GROUP))
    raise MethodError(f"unknown method {spec!r}: give a built-in name ({', '.join(known)}), "
                      f"'package.module:factory', or an entry point of the group {ENTRY_POINT_GROUP!r}")


def check_prediction(name: str, out, sample: dict) -> torch.Tensor:
    """The prediction of method ``name`` for ``sample`` as a tensor, checked: (T, S, N, 3), floating,
    finite. Raises :class:`MethodError` naming the method and what was expected."""
    t = sample["guide_positions"].shape[0]
    s, n = sample["rest_positions"].shape[:2]
    want = (t, s, n, 3)
    if not isinstance(out, torch.Tensor):
        raise MethodError(f"method {name!r} returned {type(out).__name__}; expected a tensor of shape {want} "
                          f"(T, S, N, 3) metres")
    if tuple(out.shape) != want:
        raise MethodError(f"method {name!r} returned shape {tuple(out.shape)}; expected {want} (T, S, N, 3) metres, "
                          f"world frame")
    if not out.is_floating_point():
        raise MethodError(f"method {name!r} returned {out.dtype}; expected a floating-point tensor")
    if not bool(torch.isfinite(out).all()):
        raise MethodError(f"method {name!r} returned NaN/Inf positions")
    return out


def safe_name(spec: str) -> str:
    """A method spec as a file name (``pkg.mod:factory`` → ``pkg.mod_factory``)."""
    return re.sub(r"[^A-Za-z0-9_.+-]+", "_", spec)


def frame_of(sample: dict, k: int) -> dict:
    """Frame ``k`` of a sample, as :meth:`Interpolator.step` takes it."""
    from ams_torch.geometry.pose import Pose

    return {"guide_positions": sample["guide_positions"][k], "rotation": sample["rotations"][k],
            "translation": sample["translations"][k],
            "collider_poses": [Pose(p.rotation[k], p.translation[k], check=False) for p in sample["collider_poses"]]}


def stream(method: Interpolator, sample: dict) -> torch.Tensor:
    """Run a causal method frame by frame over ``sample`` (``reset`` then ``step`` per frame).
    Returns (T, S, N, 3) m."""
    method.reset(sample)
    return torch.stack([method.step(frame_of(sample, k)) for k in range(sample["guide_positions"].shape[0])])


def describe(method: Interpolator) -> Dict[str, Optional[str]]:
    """name, class, causal and learned flags of a method, for results files; ``model`` too when the
    method says which trained weights predict (``model_id``)."""
    cls = type(method)
    out = {"name": getattr(method, "name", cls.__name__), "class": f"{cls.__module__}.{cls.__qualname__}",
           "causal": bool(getattr(method, "causal", False)), "learned": bool(getattr(method, "learned", False))}
    model = getattr(method, "model_id", None)
    if model is not None:  # which trained weights (learned methods)
        out["model"] = str(model)
    return out
