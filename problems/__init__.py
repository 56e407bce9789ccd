"""Problems by spec: the paper's systems by name, a user's own ``Problem`` by module or file.

A spec is one of

* a registered name, with an optional argument: ``"pendulum"``, ``"pendulum:linear"``, ``"cartpole"``,
  ``"nlink:7"``, ``"puma560"``, ``"baxter"``, ``"panda"``, ``"urdf:path/to/robot.urdf"``, or a name added by
  :func:`register`;
* ``"package.module:Name"`` — an attribute of an importable module;
* ``"path/to/file.py:Name"`` — an attribute of a Python file (loaded once per file version).

``Name`` is a :class:`~ocpkit.model.problem.Problem` subclass, a Problem instance or a factory returning one;
``"…:Name:arg"`` passes the string ``arg`` to the class or factory, as ``"nlink:7"`` passes ``"7"``.
"""

from __future__ import annotations

import hashlib
import importlib.util
import re
import sys
from importlib import import_module
from pathlib import Path

from ocpkit.model.problem import NotAProblemError, Problem, ProblemError, _shown, describe, where_defined, where_raised

# family -> module defining it (imported only when the family is used)
_FAMILIES = {
    "pendulum": "pendulum",
    "cartpole": "cartpole",
    "nlink": "nlink",
    "puma560": "puma560",
    "baxter": "baxter",
    "panda": "panda",
}
# family -> factory(arg) for problems registered at run time (and the URDF route)
_REGISTERED: dict = {}
_FAMILY = re.compile(r"^[A-Za-z_][\w-]*$")


def _urdf(arg=None) -> Problem:
    if not arg:
        raise ValueError("urdf needs a file, e.g. 'urdf:robot.urdf' (Problem.from_urdf takes more options)")
    return Problem.from_urdf(arg)


def names() -> list[str]:
    """The registered problem families (shipped and :func:`register`-ed)."""
    return sorted({*_FAMILIES, "urdf", *_REGISTERED})


def register(name: str, factory) -> None:
    """Make ``factory`` available as problem ``name`` everywhere a problem spec is accepted.

    ``factory(arg)`` receives the text after ``name:`` (a string) or is called without arguments for plain
    ``name``; it returns a :class:`Problem`. A Problem subclass is a factory. Names of the shipped families
    cannot be taken; registering the same name again replaces the factory.
    """
    if not isinstance(name, str) or not _FAMILY.match(name):
        raise ValueError(f"problem name must be an identifier-like string without ':' or '.', got {name!r}")
    if name in _FAMILIES or name == "urdf":
        raise ValueError(f"problem name {name!r} is taken by a shipped problem; known: {', '.join(names())}")
    if not callable(factory):
        raise TypeError(f"factory must be callable (a Problem subclass or a function), got {factory!r}")
    _REGISTERED[name] = factory


def make(spec: str) -> Problem:
    """A problem from its spec (see the module docstring), e.g. ``make("nlink:7")``, ``make("./cp.py:CartPole")``."""
    if isinstance(spec, Problem):
        return spec
    if not isinstance(spec, str):
        raise TypeError(f"problem spec must be a string, got {spec!r}")
    if not spec:
        raise ValueError(f"problem spec is empty; known problems: {', '.join(names())}")
    family, _, arg = spec.partition(":")
    if family in _FAMILIES:
        return import_module(f"ocpkit.problems.{_FAMILIES[family]}").REGISTRY[family](arg or None)
    if family == "urdf":
        return _urdf(arg or None)
    if family in _REGISTERED:
        return _build(_REGISTERED[family], arg or None, spec)
    if ".py:" in spec or spec.endswith(".py"):
        path, _, rest = spec.rpartition(".py:") if ".py:" in spec else (spec[:-3], "", "")
        name, _, arg = rest.partition(":")
        return _build(_attribute(_load_file(path + ".py", spec), name, spec), arg or None, spec)
    if ":" in spec and ("." in family or _module_exists(family)):
        name, _, arg = arg.partition(":")
        try:
            module = import_module(family)
        except ImportError as exc:
            raise ValueError(f"problem spec {spec!r}: cannot import module {family!r}: {exc}") from None
        except Exception as exc:  # the user's module raised while it was imported
            raise _failed(spec, f"importing module {family!r}", exc) from exc
        return _build(_attribute(module, name, spec), arg or None, spec)
    raise ValueError(
        f"unknown problem {spec!r}; known: {', '.join(names())}, or a Problem of your own as "
        "'package.module:Name' or 'path/to/file.py:Name'"
    )


def _module_exists(name: str) -> bool:
    try:
        return importlib.util.find_spec(name) is not None
    except (ImportError, ValueError):
        return False


def _load_file(path: str, spec: str):
    """The module of a Python file, loaded once per (absolute path, modification time)."""
    file = Path(path).expanduser()
    if not file.is_file():
        raise ValueError(f"problem spec {spec!r}: no such file {str(file)!r}")
    file = file.resolve()
    stamp = f"{file}:{file.stat().st_mtime_ns}"
    stem = re.sub(r"\W", "_", file.stem)
    module_name = f"ocpkit_user_{stem}_{hashlib.sha1(stamp.encode()).hexdigest()[:10]}"
    if module_name not in sys.modules:
        loader_spec = importlib.util.spec_from_file_location(module_name, file)
        module = importlib.util.module_from_spec(loader_spec)
        sys.modules[module_name] = module  # before exec: dataclasses and pickling look the module up
        try:
            loader_spec.loader.exec_module(module)
        except BaseException as exc:
            del sys.modules[module_name]
            if isinstance(exc, Exception):  # the user's file raised (or is not valid Python) while it was imported
                raise _failed(spec, f"importing {_shown(str(file))}", exc, own=[file]) from exc
            raise
    return sys.modules[module_name]


def _attribute(module, name: str, spec: str):
    if not name:
        raise ValueError(
            f"problem spec {spec!r} names no problem: add ':Name' (a Problem subclass, instance or factory)"
        )
    if not hasattr(module, name):
        found = sorted(
            k
            for k, v in vars(module).items()
            if isinstance(v, Problem) or (isinstance(v, type) and issubclass(v, Problem) and v is not Problem)
        )
        where = module.__name__ if not hasattr(module, "__file__") else module.__file__
        raise ValueError(
            f"problem spec {spec!r}: {where} has no {name!r}; problems there: {', '.join(found) or 'none'}"
        )
    return getattr(module, name)


def _build(obj, arg, spec: str) -> Problem:
    if isinstance(obj, Problem):
        if arg is not None:
            raise ValueError(f"problem spec {spec!r}: {type(obj).__name__} is an instance and takes no argument")
        problem = obj
    elif callable(obj):
        call = f"{getattr(obj, '__qualname__', type(obj).__name__)}({'' if arg is None else repr(arg)})"
        try:
            problem = obj() if arg is None else obj(arg)
        except ProblemError:
            raise
        except Exception as exc:  # the user's class or factory raised
            raise _failed(spec, call, exc) from exc
    else:
        raise NotAProblemError(f"problem spec {spec!r} names {obj!r}, not a Problem subclass, instance or factory")
    if not isinstance(problem, Problem):
        where = where_defined(obj)
        raise NotAProblemError(
            f"problem spec {spec!r}: {call} returned {type(problem).__name__}, not an ocpkit.Problem"
            + (f" ({call.split('(')[0]} is defined at {where})" if where else ""),
            where,
        )
    return problem


def _failed(spec: str, doing: str, exc: Exception, own=()) -> ProblemError:
    """The one-line ProblemError for user code that raised while ``doing``: the spec, file:line and the exception."""
    where = where_raised(exc, own)
    at = f" at {where}" if where else ""
    return ProblemError(f"problem spec {spec!r}: {doing} failed{at}: {describe(exc)}", where)


def filename(spec: str) -> str:
    """A file-name-safe form of a problem spec ("nlink:7" -> "nlink_7", "./cp.py:CartPole" -> "cp_py_CartPole")."""
    return re.sub(r"[^\w-]+", "_", str(spec)).strip("_") or "problem"
