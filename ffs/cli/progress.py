"""Per-file progress bars with the current stage (rich, on a terminal only)."""

from __future__ import annotations

from typing import Any


class Display:
    """Progress bars: one per running file, and one for the whole batch.

    Args:
        enabled: Draw bars (stderr is a terminal and no ``-q``); otherwise every method is
            a no-op. Without the optional ``rich`` package there are no bars either.
        total: How many files the batch has (an overall bar when more than one).
    """

    def __init__(self, enabled: bool, total: int) -> None:
        self.progress: Any = None
        self.tasks: dict[int, Any] = {}
        self.names: dict[int, str] = {}
        if not enabled:
            return
        try:
            from rich.console import Console
            from rich.progress import (
                BarColumn,
                MofNCompleteColumn,
                Progress,
                TextColumn,
                TimeElapsedColumn,
            )
        except ImportError:  # the progress library is optional: no bars then
            return
        self.progress = Progress(TextColumn("{task.description}"), BarColumn(),
                                 MofNCompleteColumn() if total > 1 else TextColumn(""),
                                 TimeElapsedColumn(), console=Console(stderr=True),
                                 transient=True)
        self.overall = self.progress.add_task("all files", total=total) if total > 1 else None
        self.progress.start()

    def name(self, index: int, name: str) -> None:
        """Label item ``index``'s bar with ``name``."""
        self.names[index] = name

    def event(self, index: int, stage: str, fraction: float) -> None:
        """Item ``index`` is at ``stage``, ``fraction`` (0 to 1) done."""
        if self.progress is None:
            return
        label = f"{self.names.get(index, index)} [cyan]{stage}[/]"
        if index not in self.tasks:
            self.tasks[index] = self.progress.add_task(label, total=1.0)
        self.progress.update(self.tasks[index], description=label, completed=fraction)

    def done(self, index: int) -> None:
        """Item ``index`` finished (in any way): its bar goes, the overall one advances."""
        if self.progress is None:
            return
        if index in self.tasks:
            self.progress.remove_task(self.tasks.pop(index))
        if self.overall is not None:
            self.progress.advance(self.overall)

    def close(self) -> None:
        """Remove the bars from the terminal."""
        if self.progress is not None:
            self.progress.stop()
