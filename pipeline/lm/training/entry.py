"""The one entry point of training: `train(request)` builds (or loads) the model the request names and
fine-tunes it. The finetune step calls it in-process, or `launch` runs it under ``accelerate launch`` (one
process per device, e.g. FSDP) as ``python -m pipeline.lm.training --request <request.json>``."""

from __future__ import annotations

import argparse
import json
import logging
import os
import subprocess
import sys
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Sequence

from pipeline.lm.chat import read_conversations
from pipeline.lm.model_settings import ModelSettings
from pipeline.lm.models import load_tokenizer, make_model
from pipeline.lm.training.settings import TrainSettings
from pipeline.lm.training.result import RESULT_FILE, TrainResult
from pipeline.lm.training.trainer import finetune

log = logging.getLogger(__name__)

REQUEST_FILE = "train_request.json"


@dataclass
class TrainRequest:
    """Everything a training process needs, in a form that survives a trip through a JSON file."""

    model: ModelSettings
    train: TrainSettings
    seed: int
    data: str            # the training conversations (JSONL)
    tokenizer_dir: str   # the tokenizer, saved
    output_dir: str

    def save(self, path: str | Path) -> Path:
        plain = {"model": self.model.to_dict(), "train": self.train.to_dict(), "seed": self.seed, "data": self.data,
                 "tokenizer_dir": self.tokenizer_dir, "output_dir": self.output_dir}
        Path(path).write_text(json.dumps(plain, indent=2) + "\n")
        return Path(path)

    @classmethod
    def load(cls, path: str | Path) -> "TrainRequest":
        plain = json.loads(Path(path).read_text())
        return cls(model=ModelSettings(**plain["model"]), train=TrainSettings.from_dict(plain["train"]), seed=plain["seed"],
                   data=plain["data"], tokenizer_dir=plain["tokenizer_dir"], output_dir=plain["output_dir"])


def train(request: TrainRequest, conversations: list[list[dict]] | None = None) -> TrainResult:
    """Build or load the model, then fine-tune it on ``request.data`` (or ``conversations``, already read)."""
    tokenizer = load_tokenizer(request.tokenizer_dir)
    model = make_model(request.model, tokenizer, seed=request.seed)
    if conversations is None:
        conversations = read_conversations(request.data)
    return finetune(model, tokenizer, request.model.chat_format, conversations, request.train, request.output_dir,
                    seed=request.seed, max_length=request.model.max_length)


def launch(request: TrainRequest, env: dict[str, str] | None = None) -> TrainResult:
    """Run `train` under ``accelerate launch --config_file <request.train.accelerate_config>``; ``env`` is
    added to the processes' environment (e.g. ``MLFLOW_TRACKING_URI`` and ``MLFLOW_RUN_ID``, so rank 0's
    MLflowCallback logs into the caller's run)."""
    path = request.save(Path(request.output_dir) / REQUEST_FILE)
    command = [sys.executable, "-m", "accelerate.commands.launch", "--config_file",
               str(request.train.accelerate_config), "-m", "pipeline.lm.training", "--request", str(path)]
    subprocess.run(command, check=True, env={**os.environ, **(env or {})})
    return TrainResult(**json.loads((Path(request.output_dir) / RESULT_FILE).read_text()))


def main(argv: Sequence[str] | None = None) -> None:
    """``python -m pipeline.lm.training --request request.json`` (or under ``accelerate launch -m``)."""
    parser = argparse.ArgumentParser(prog="python -m pipeline.lm.training", description=__doc__.splitlines()[0])
    parser.add_argument("--request", required=True, help="a TrainRequest saved as JSON")
    args = parser.parse_args(argv)
    logging.basicConfig(level=logging.INFO)
    request = TrainRequest.load(args.request)
    result = train(request)
    if int(os.environ.get("RANK", "0")) == 0:
        (Path(request.output_dir) / RESULT_FILE).write_text(json.dumps(asdict(result), indent=2) + "\n")
        print(json.dumps(asdict(result)))
