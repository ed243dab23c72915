"""``python -m pipeline.lm.training.precompile``: one training step of a model shaped as a job's, on made-up
conversations, in a process of its own, so that inductor's on-disk caches hold the job's compiled decoder layer
before the job's first step asks for it (`pipeline.lm.training.compile.compile_beside` hands it the job's settings,
beside the data-build).

The process starts with the command line (`pipeline.lm.training.beside.start_early`, from ``python -m
pipeline.run``): it imports torch, transformers and the trainer while the job's own process imports, on the core
that would otherwise wait, then reads the job's settings (one line of JSON) from its standard input; an empty
input, or none within `SETTINGS_TIMEOUT`, ends it (a job that compiles nothing here).

The compiled layer does not depend on the words: the same layer class and sizes, the same training settings (bf16
as the job decided it, batch parts, the part threads' C++ wrapper) and the same number of torch threads give the
same graphs, so the job's own compile finds them (dynamo still traces; inductor's and AOTAutograd's caches give
the rest). Nothing of it reaches the job but those caches; a failure here costs the job nothing but its own
compile.
"""

from __future__ import annotations

import json
import os
import select
import shutil
import sys
import tempfile
from dataclasses import replace
from pathlib import Path
from typing import Sequence

# One conversation for each row of a batch: each a few dozen words, no two of one length.
_CONVERSATIONS = 16


def made_up_conversations(frame: int, newlines: str) -> list[list[dict]]:
    """`_CONVERSATIONS` conversations made of the frame's cells (words every scratch tokenizer has)."""
    from pipeline.lm.tokenizer import coverage_text

    cells = coverage_text(frame, newlines).split(")")[:-1]
    cells = [cell.lstrip("\n") + ")" for cell in cells]
    out = []
    for i in range(_CONVERSATIONS):
        human = " ".join(cells[i:i + 8])
        gpt = "\n".join(cells[i:i + 20 + 3 * i])
        out.append([{"from": "human", "value": human}, {"from": "gpt", "value": gpt}])
    return out


def main(argv: Sequence[str] | None = None) -> None:
    argv = sys.argv[1:] if argv is None else argv
    folder = Path(argv[0])
    import torch

    from pipeline.lm.model_settings import ModelSettings
    from pipeline.lm.models import make_model, make_tokenizer
    from pipeline.lm.training.beside import SETTINGS_TIMEOUT
    from pipeline.lm.training.compile import warm_compiler
    from pipeline.lm.training.settings import TrainSettings
    from pipeline.lm.training.trainer import finetune

    line = sys.stdin.readline() if select.select([sys.stdin], [], [], SETTINGS_TIMEOUT)[0] else ""
    if not line.strip():  # no settings: the job compiles nothing here (or its jobs run in other processes)
        shutil.rmtree(folder, ignore_errors=True)
        return
    plain = json.loads(line)
    # Inductor's checks of the C++ compiler (g++) while the model is built and dynamo traces: after the settings,
    # so no g++ ran beside the job's measure of its matmul peaks (`use_bf16`).
    warm_compiler(wait=False)
    torch.set_num_threads(plain["threads"])
    model_settings = ModelSettings(**plain["model"])
    train = TrainSettings.from_dict(plain["train"])
    # One step, nothing reported or kept; bf16 as the job decided it (measured there, with nothing beside it).
    train = replace(train, max_steps=1, report_to=[], eval_fraction=0.0, save_steps=10**9, save_total_limit=None,
                    log_checkpoints=False, bf16=plain["bf16"], bf16_when_faster=False, torch_threads=None)
    conversations = made_up_conversations(plain["frame"], model_settings.newlines)
    tokenizer = make_tokenizer(model_settings, (turn["value"] for turns in conversations for turn in turns),
                               plain["frame"])
    model = make_model(model_settings, tokenizer, seed=0)
    with tempfile.TemporaryDirectory(prefix="cogmap-precompile-") as out:
        finetune(model, tokenizer, model_settings.chat_format, conversations, train, out, seed=0,
                 max_length=model_settings.max_length, callbacks=[_exit_after_the_step(out)])


def _exit_after_the_step(folder: str):
    """A callback: once the step has run, the caches hold what it compiled, so the process ends there, ``folder``
    removed, without the rest of `finetune` (saving the model) or the interpreter's teardown (inductor's compile
    workers)."""
    from transformers import TrainerCallback

    class ExitAfterTheStep(TrainerCallback):
        def on_step_end(self, args, state, control, **kwargs):
            shutil.rmtree(folder, ignore_errors=True)
            sys.stdout.flush()
            sys.stderr.flush()
            os._exit(0)

    return ExitAfterTheStep()


if __name__ == "__main__":
    main()
