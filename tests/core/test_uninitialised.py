"""Every public method and property of the core's classes, called on an object whose __init__
never ran (Class.__new__(Class)), raises TypeError instead of crashing the interpreter.

Each call runs in its own subprocess, so that a crash fails that test instead of ending pytest.
The members are enumerated from the classes themselves: a new method fails
test_every_method_has_a_call until it is given arguments here, and is then checked like the
others."""

import inspect
import subprocess
import sys
import textwrap

import pytest

from soulctl import _core

# Every class the module has: a new class fails here until it is given a SETUP and its CALLS.
CLASSES = tuple(sorted(n for n in dir(_core) if isinstance(getattr(_core, n), type)))

# A constructed object `ok` of each class ...
SETUP = {
    "SlopeComputer": "ok = SlopeComputer(np.array([[[1, 1], [0, 1], [1, 0], [0, 0]]]), (2, 2))",
    "RealTimeController": "ok = RealTimeController(np.eye(2), np.ones((2, 3)), np.ones((4, 2)))",
    "InfluenceFunctions": "ok = InfluenceFunctions(np.array([0, 1, 2]), np.array([0, 1]), np.ones(2), 2)",
}
# ... and, for each method, a call with arguments that are valid for `ok`: on an uninitialised
# object nothing but the object itself can then be refused.
CALLS = {
    "SlopeComputer": {
        "compute": "{}.compute(np.ones(ok.frame_shape, np.float32), out=np.empty(2, np.float32))",
        "set_background": "{}.set_background(np.zeros(ok.frame_shape, np.float32))",
        "clear_background": "{}.clear_background()",
        "set_reference": "{}.set_reference(np.zeros(2, np.float32))",
        "clear_reference": "{}.clear_reference()",
    },
    "RealTimeController": {
        "step": "{}.step(np.ones(3, np.float32), out=np.empty(4, np.float32))",
        "run": "{}.run(np.ones((5, 3), np.float32), state_gains=np.ones((5, 2), np.float32))",
        "set_state_gains": "{}.set_state_gains(np.ones(2, np.float32))",
        "reset": "{}.reset()",
    },
    "InfluenceFunctions": {
        "shape": "{}.shape(np.ones(2))",
        "adjoint": "{}.adjoint(np.ones(2))",
        "shape_and_adjoint": "{}.shape_and_adjoint(np.ones(2), np.ones(2))",
    },
}


def public_members(cls_name):
    """(name, is_property) of every public attribute of the class."""
    cls = getattr(_core, cls_name)
    return [(n, isinstance(inspect.getattr_static(cls, n), property)) for n in dir(cls) if not n.startswith("_")]


MEMBERS = [(c, n, prop) for c in CLASSES for n, prop in public_members(c)]


def run_python(code, tmp_path):
    # cwd: a folder without the source tree, so the subprocess imports the installed package.
    return subprocess.run([sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, timeout=120)


def test_every_method_has_a_call():
    for c in CLASSES:
        methods = {n for n, prop in public_members(c) if not prop}
        assert methods == set(CALLS[c]), f"{c}: give every public method a call in CALLS"
    assert set(CLASSES) == set(SETUP) == set(CALLS), "give every class of the core a SETUP and its CALLS"
    assert len(MEMBERS) >= 31  # 14 + 11 + 6 today: the enumeration found the properties too


@pytest.mark.slow
@pytest.mark.parametrize("cls_name, member, is_property", MEMBERS, ids=[f"{c}.{n}" for c, n, _ in MEMBERS])
def test_member_of_uninitialised_object_raises_type_error(cls_name, member, is_property, tmp_path):
    call = f"{{}}.{member}" if is_property else CALLS[cls_name][member]
    code = textwrap.dedent(f"""
        import numpy as np
        from soulctl._core import {cls_name}
        {SETUP[cls_name]}
        {call.format("ok")}  # the same call works on a constructed object
        obj = {cls_name}.__new__({cls_name})
        try:
            {call.format("obj")}
        except TypeError as e:
            print("TypeError:", e)
        else:
            print("no error")
    """)
    r = run_python(code, tmp_path)
    assert r.returncode == 0, f"exit status {r.returncode}\n{r.stdout}\n{r.stderr}"
    assert r.stdout.strip() == f"TypeError: {cls_name} object is not initialised (its __init__ was not called)"


def test_subclass_instance_without_init_raises_type_error(tmp_path):
    code = textwrap.dedent("""
        import numpy as np
        from soulctl._core import RealTimeController, SlopeComputer

        class Controller(RealTimeController):
            pass

        class Slopes(SlopeComputer):
            pass

        for obj, call in ((Controller.__new__(Controller), lambda o: o.step(np.ones(3, np.float32))),
                          (Slopes.__new__(Slopes), lambda o: o.clear_background())):
            try:
                call(obj)
            except TypeError as e:
                print(e)
    """)
    r = run_python(code, tmp_path)
    assert r.returncode == 0, f"exit status {r.returncode}\n{r.stdout}\n{r.stderr}"
    assert r.stdout.splitlines() == [
        "Controller object is not initialised (its __init__ was not called)",
        "Slopes object is not initialised (its __init__ was not called)",
    ]


def test_methods_still_refuse_other_objects():
    with pytest.raises(TypeError, match="incompatible function arguments"):
        _core.RealTimeController.reset(object())
