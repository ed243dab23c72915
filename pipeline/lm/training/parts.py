"""A training batch cut into parts that Python threads compute side by side (`TrainSettings.batch_threads`).

On a small CPU one process does not use its cores well: the compiled layers' element-wise kernels and small
matrices scale poorly across intra-op threads, while two processes on one thread each run at about 1.4x the
throughput of one process on two (README, Speed). Python threads get that within one process when the work
releases the interpreter lock: torch's operators do, and inductor's kernels do when the compiled graph runs
from its C++ wrapper (``cpp_wrapper``), which `compiled_blocks` then asks for.

Each part is computed on one intra-op thread, its loss normalized by the whole batch's label count, and its
gradients accumulate into the same ``.grad``; with two parts the sum is the same whichever finishes first
(floating-point addition of two terms commutes), so a run is deterministic. Where the process has fewer
threads than parts (a grid job on one thread), the batch stays whole: parts one after the other on one thread
ran 0.97x. Dynamo must not compile in two threads at once (it deadlocked here), so the first step's parts run
one after the other; later steps run under ``fail_on_recompile`` and redo, one at a time, a part that would
recompile (it fails in its forward, before its gradients exist). Between the parts the same threads take
Muon's step (`PartThreads.map`; `pipeline.lm.training.optim.MuonAdamW.side_by_side`), and the caller's own thread
runs on one intra-op thread meanwhile (`pipeline.lm.training.trainer`): an idle intra-op thread of the caller's
spins on a core after each of its parallel kernels, and that was taken from a part.
"""

from __future__ import annotations

import contextlib
import queue
import threading
from typing import Callable, ContextManager, Sequence

import torch


def split_rows(inputs: dict[str, torch.Tensor], parts: int, multiple: int = 1) -> list[dict[str, torch.Tensor]]:
    """``inputs`` (a right-padded batch: ``input_ids``, ``labels``, optional ``attention_mask`` and
    ``position_ids``) cut into ``parts`` runs of consecutive rows (sizes differ by at most one; no empty part),
    each cut to its own longest row rounded up to a ``multiple`` when a mask says where the rows end (padding
    only ever follows a row's real tokens, so a causal model computes the same for them)."""
    rows = inputs["input_ids"].shape[0]
    bounds = [round(i * rows / parts) for i in range(parts + 1)]
    out = []
    for start, stop in zip(bounds, bounds[1:]):
        if stop == start:
            continue
        part = {key: value[start:stop] for key, value in inputs.items()}
        mask = part.get("attention_mask")
        if mask is not None:
            width = min(-(-int(mask.sum(dim=1).max()) // multiple) * multiple, mask.shape[1])
            part = {key: value[:, :width] for key, value in part.items()}
        out.append(part)
    return out


class PartThreads:
    """``n`` daemon threads, each with ``intra_op`` torch threads, that run one call each per `run`."""

    def __init__(self, n: int, intra_op: int = 1, settings: Callable[[], ContextManager] = contextlib.nullcontext):
        """``settings``: a context each thread runs its calls in, for its whole life (torch keeps its compiler's
        settings per thread, so those the caller patched do not reach these threads)."""
        self.parts = n
        self._inbox = [queue.Queue() for _ in range(n)]
        self._done: queue.Queue = queue.Queue()
        self._compiled = False
        for i in range(n):
            threading.Thread(target=self._work, args=(i, intra_op, settings), daemon=True,
                             name=f"batch-part-{i}").start()

    def _work(self, i: int, intra_op: int, settings: Callable[[], ContextManager]) -> None:
        torch.set_num_threads(intra_op)  # this thread's own setting; the caller's threads keep theirs
        with settings():
            while True:
                call = self._inbox[i].get()
                if call is None:
                    return
                try:
                    self._done.put((True, call()))
                except BaseException as error:  # handed to the caller, raised there
                    self._done.put((False, error))

    def run(self, calls: Sequence[Callable]) -> list:
        """Each call's result, in order. The calls run side by side; the first time, and for any call that
        would make dynamo compile again, one at a time on the first thread."""
        if not self._compiled:
            results = [self._one(call) for call in calls]
            self._compiled = True
            return results
        with torch.compiler.set_stance("fail_on_recompile"):
            outcome = self._side_by_side(calls)
        return [value if ok else self._one(calls[index]) for index, (ok, value) in enumerate(outcome)]

    def map(self, calls: Sequence[Callable], meanwhile: Callable[[], object] | None = None) -> list:
        """Each call's result, in order, the calls side by side (for work that compiles nothing: Muon's step);
        the first error a call raised is raised here, once all have finished. ``meanwhile`` runs on the caller's
        thread while they work (its error raised once they have finished)."""
        outcome = self._side_by_side(calls, meanwhile)
        for ok, value in outcome:
            if not ok:
                raise value
        return [value for _, value in outcome]

    def _side_by_side(self, calls: Sequence[Callable], meanwhile: Callable[[], object] | None = None
                      ) -> list[tuple[bool, object]]:
        for index, call in enumerate(calls):
            self._inbox[index % len(self._inbox)].put(_Tagged(index, call))
        error = None
        if meanwhile is not None:
            try:
                meanwhile()
            except BaseException as raised:  # the calls finish first: their threads stay in step with the inboxes
                error = raised
        outcome: list = [None] * len(calls)
        for _ in calls:
            ok, value = self._done.get()
            index, result = value if ok else (value.part_index, value)
            outcome[index] = (ok, result)
        if error is not None:
            raise error
        for ok, result in outcome:
            if not ok and not _is_recompile(result):
                raise result
        return outcome

    def _one(self, call: Callable):
        self._inbox[0].put(_Tagged(0, call))
        ok, value = self._done.get()
        if not ok:
            raise value
        return value[1]

    def close(self) -> None:
        for inbox in self._inbox:
            inbox.put(None)


class _Tagged:
    """A call that returns (its index, its result) and tags an exception it raises with its index."""

    def __init__(self, index: int, call: Callable):
        self.index, self.call = index, call

    def __call__(self):
        try:
            return self.index, self.call()
        except BaseException as error:
            error.part_index = self.index
            raise


def _is_recompile(error: BaseException) -> bool:
    return "fail_on_recompile" in str(error)  # dynamo raises a RuntimeError naming the stance
