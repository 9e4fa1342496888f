"""service.methods.lazy: functions named "module:attr" and lazy package exports."""

import pytest

from service.methods.lazy import LazyFunction, resolve


def test_resolve_and_call_dotted_targets():
    import os.path

    assert resolve("os.path:join") is os.path.join
    assert resolve("os:path.join") is os.path.join
    assert resolve("os.path") is os.path
    join = LazyFunction("os.path:join")
    assert join("a", "b") == os.path.join("a", "b") and join.function is os.path.join
    assert LazyFunction("os.path:join") == join


def test_package_exports_resolve_and_bind_and_unknown_names_raise():
    from service.methods import correspondence, pose_space

    assert pose_space.PsdParams.__module__ == "service.methods.pose_space.params"
    # the function named as its submodule: the function, as the eager import bound it
    from service.methods.correspondence import correspond
    assert callable(correspond) and correspondence.correspond is correspond
    with pytest.raises(AttributeError, match="has no attribute 'nothing'"):
        pose_space.nothing  # noqa: B018
    from service.methods.pose_space import rbf          # a submodule still imports
    assert rbf.__name__ == "service.methods.pose_space.rbf"
