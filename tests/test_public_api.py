"""The public API documents itself: docstrings and type hints on every public name.

What counts as public, per module found by ``pkgutil.walk_packages`` over ``msf_torch``:

* the names in the module's ``__all__``; a module without ``__all__``: the names not starting
  with ``_`` that are defined in that module (not imported into it);
* of those, functions and classes defined inside ``msf_torch`` (a re-export is checked once,
  under the module that defines it);
* of a public class, the methods, static/class methods and properties defined in the class
  body itself or in a private (``_``-named) ``msf_torch`` base it inherits them from, whose
  names do not start with ``_``, plus such an ``__init__`` when it takes parameters. Members
  inherited from public classes are checked there; other dunder methods are skipped.

What is asserted:

* every module has a module docstring;
* every public function, class, method and property has a non-empty docstring;
* every parameter is annotated except the implicit first one of a method (``self``/``cls``);
  ``*args``/``**kwargs`` need annotations too;
* every function and method has a return annotation (``-> None`` counts); properties and
  ``__init__`` are exempt;
* ``__init__`` with parameters: annotations as above, and either ``__init__`` has its own
  docstring or every parameter name appears in the class docstring;
* dataclasses: the class docstring is required; the generated ``__init__`` is not checked
  (its fields are annotated by construction).

Nothing is exempt: Lightning hooks that ``msf_torch`` overrides are documented and typed too.
"""

from __future__ import annotations

import dataclasses
import importlib
import inspect
import pkgutil
import re
import types
import typing

import msf_torch


def _modules() -> list[types.ModuleType]:
    found = [msf_torch]
    for info in pkgutil.walk_packages(msf_torch.__path__, prefix="msf_torch."):
        found.append(importlib.import_module(info.name))
    return found


def _public_objects(module: types.ModuleType) -> list[object]:
    names = getattr(module, "__all__", None)
    if names is None:
        names = [
            name
            for name, obj in vars(module).items()
            if not name.startswith("_") and getattr(obj, "__module__", None) == module.__name__
        ]
    objects = []
    for name in names:
        obj = getattr(module, name)
        if not (inspect.isfunction(obj) or inspect.isclass(obj)):
            continue
        if not getattr(obj, "__module__", "").startswith("msf_torch"):
            continue
        objects.append(obj)
    return objects


def _doc(obj: object) -> str:
    """The object's own docstring (not inherited), "" when it has none or when it is the
    signature that ``dataclasses`` / ``NamedTuple`` write in place of a missing one."""
    doc = inspect.cleandoc(obj.__doc__) if getattr(obj, "__doc__", None) else ""
    if inspect.isclass(obj) and doc:
        if dataclasses.is_dataclass(obj):
            generated = obj.__name__ + str(inspect.signature(obj)).replace(" -> None", "")
        elif issubclass(obj, tuple) and hasattr(obj, "_fields"):
            generated = f"{obj.__name__}({', '.join(obj._fields)}{',' * (len(obj._fields) == 1)})"
        else:
            generated = None
        if doc == generated:
            return ""
    return doc.strip()


def _signature_problems(
    function: types.FunctionType, is_method: bool, needs_return: bool
) -> list[str]:
    problems = []
    signature = inspect.signature(function)
    parameters = list(signature.parameters.values())
    if is_method and parameters:
        parameters = parameters[1:]
    missing = [p.name for p in parameters if p.annotation is inspect.Parameter.empty]
    if missing:
        problems.append("parameter annotations missing: " + ", ".join(missing))
    if needs_return and signature.return_annotation is inspect.Signature.empty:
        problems.append("return annotation missing")
    return problems


def _own_members(cls: type) -> dict[str, object]:
    """Members the class itself defines, plus those it gets from a private ``msf_torch`` base
    (``_Unary`` and the like) that no public base already brings (those are checked under
    that base); the first definition in the MRO wins."""
    ours = [k for k in cls.__mro__[1:] if k.__module__.startswith("msf_torch")]
    covered = {id(m) for k in ours if not k.__name__.startswith("_") for m in k.__mro__}
    members: dict[str, object] = {}
    seen: set[str] = set()
    for klass in cls.__mro__:
        private_base = klass in ours and klass.__name__.startswith("_") and id(klass) not in covered
        for name, member in vars(klass).items():
            if name in seen:
                continue
            seen.add(name)
            if klass is cls or private_base:
                members[name] = member
    return members


def _function_problems(function: object, where: str, is_method: bool) -> list[str]:
    """A public function's or method's missing docstring and annotations."""
    offenders = [] if _doc(function) else [f"{where}: docstring missing"]
    return offenders + [
        f"{where}: {p}"
        for p in _signature_problems(function, is_method=is_method, needs_return=True)
    ]


def _class_problems(cls: type, where: str) -> list[str]:
    offenders = []
    class_doc = _doc(cls)
    if not class_doc:
        offenders.append(f"{where}: class docstring missing")
    generated_init = dataclasses.is_dataclass(cls) and cls.__dataclass_params__.init
    for name, member in _own_members(cls).items():
        if name.startswith("_") and name != "__init__":
            continue
        qualname = f"{where}.{name}"
        if isinstance(member, property):
            if not _doc(member):
                offenders.append(f"{qualname}: property docstring missing")
            if member.fget is not None:
                offenders += [
                    f"{qualname}: {p}"
                    for p in _signature_problems(member.fget, is_method=True, needs_return=False)
                ]
            continue
        is_method = True
        if isinstance(member, staticmethod):
            member, is_method = member.__func__, False
        elif isinstance(member, classmethod):
            member = member.__func__
        if not inspect.isfunction(member):
            continue
        if name == "__init__":
            if generated_init:
                continue
            parameters = list(inspect.signature(member).parameters)[1:]
            if not parameters:
                continue
            undocumented = [p for p in parameters if not re.search(rf"\b{p}\b", class_doc)]
            if not _doc(member) and undocumented:
                offenders.append(
                    f"{qualname}: no __init__ docstring and the class docstring does not name "
                    + ", ".join(undocumented)
                )
            offenders += [
                f"{qualname}: {p}"
                for p in _signature_problems(member, is_method=True, needs_return=False)
            ]
            continue
        offenders += _function_problems(member, qualname, is_method)
    return offenders


def public_api_offenders() -> list[str]:
    """Every public-API offender as ``module.qualname: what is missing``."""
    offenders = []
    seen: set[int] = set()
    for module in _modules():
        if not (module.__doc__ or "").strip():
            offenders.append(f"{module.__name__}: module docstring missing")
        for obj in _public_objects(module):
            if id(obj) in seen:
                continue
            seen.add(id(obj))
            where = f"{obj.__module__}.{obj.__qualname__}"
            if inspect.isclass(obj):
                offenders += _class_problems(obj, where)
                continue
            offenders += _function_problems(obj, where, is_method=False)
    return offenders


def test_public_api_is_documented_and_typed():
    walked = {module.__name__ for module in _modules()}
    assert {"msf_torch.types", "msf_torch.frontend.init", "msf_torch.backend.factors"} <= walked
    offenders = public_api_offenders()
    assert not offenders, f"{len(offenders)} public-API offenders:\n" + "\n".join(offenders)


def test_checker_catches_an_undocumented_untyped_function():
    def bare(x, *rest):
        return x

    problems = _signature_problems(bare, is_method=False, needs_return=True)
    assert problems == ["parameter annotations missing: x, rest", "return annotation missing"]

    class Undocumented:
        def __init__(self, gain):
            self.gain = gain

        @property
        def doubled(self):
            return 2 * self.gain

        def scaled(self, value: float) -> float:
            return self.gain * value

    @dataclasses.dataclass
    class Fields:
        gain: float

    class Row(typing.NamedTuple):
        gain: float

    assert _class_problems(Fields, "m.Fields") == ["m.Fields: class docstring missing"]
    assert _class_problems(Row, "m.Row") == ["m.Row: class docstring missing"]

    class _Base:
        def shared(self, value):
            return value

    class Public(_Base):
        """Documented, but inherits an undocumented, untyped method from a private base."""

    _Base.__module__ = Public.__module__ = "msf_torch.example"
    assert _class_problems(Public, "m.Public") == [
        "m.Public.shared: docstring missing",
        "m.Public.shared: parameter annotations missing: value",
        "m.Public.shared: return annotation missing",
    ]

    found = _class_problems(Undocumented, "m.Undocumented")
    assert found == [
        "m.Undocumented: class docstring missing",
        "m.Undocumented.__init__: no __init__ docstring and the class docstring does not name gain",
        "m.Undocumented.__init__: parameter annotations missing: gain",
        "m.Undocumented.doubled: property docstring missing",
        "m.Undocumented.scaled: docstring missing",
    ]
