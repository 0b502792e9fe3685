import pytest

from kkl_bench.registry import estimators


@pytest.fixture
def register_estimator(monkeypatch):
    """Register an estimator class under a name for one test only."""

    def register(name, cls):
        monkeypatch.setitem(estimators._loaded, name, cls)
        return cls

    return register
