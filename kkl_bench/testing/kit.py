"""What the conformance kits share: a set of named checks, run one by one, and the line a
failed check reads as."""

from __future__ import annotations

from collections.abc import Callable, Iterable, Iterator


class NamedChecks:
    """A kit whose checks are its methods named ``check_*``."""

    def checks(self) -> Iterator[tuple[str, Callable[[], None]]]:
        """``(name, check)`` pairs, by name; a check raises AssertionError on failure."""
        for name in sorted(dir(self)):
            if name.startswith("check_"):
                yield name, getattr(self, name)


def outcomes(
    checks: Iterable[tuple[str, Callable[[], None]]],
) -> Iterator[tuple[str, BaseException | None]]:
    """Run each check; ``(name, None)`` on success, ``(name, error)`` on failure."""
    for name, check in checks:
        try:
            check()
        except Exception as error:
            yield name, error
        else:
            yield name, None


def describe(error: BaseException) -> str:
    """``Type: message`` of a failed check, as FAIL lines show it."""
    return f"{type(error).__name__}: {error}"
