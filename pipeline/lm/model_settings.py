"""The model's settings: its kind and size (or where it is), its context, its chat format and prompt form.

Kept apart from `pipeline.lm.models` (torch and transformers) so the config can be built and checked without
importing either.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, fields
from enum import Enum
from typing import Optional

from pipeline.core.checks import SettingError, require
from pipeline.core.texts import DEFAULT_PROMPT, PLAN_FORMS, PROMPTS, STEP_HEADERS
from pipeline.lm.chat import ChatFormat

DTYPES = ("float32", "bfloat16", "float16")
# transformers' attention kernels; "flash_attention_2" needs the flash-attn package and a GPU.
ATTENTION_IMPLEMENTATIONS = ("sdpa", "eager", "flash_attention_2")
# How the finetune step logs the model in MLflow: the transformers flavour (weights copied) or a reference to
# the run's model/ artifacts (for large models).
LOG_MODEL_CHOICES = ("transformers", "reference")
# How a scratch model knows positions: rotary embeddings in every layer (Llama's), in none (NoPE: the causal
# mask alone tells order; Kazemnejad et al. 2023), or in every other layer starting with the first
# ("alternate"). The last two build transformers' SmolLM3, a Llama with per-layer RoPE switches.
POSITIONS = ("rope", "nope", "alternate")
# How a scratch model scales its attention logits: by 1/sqrt(head size) alone (Llama's), or also by log(n), n the
# number of keys a query sees (pipeline.lm.models.log_length_attention: Scalable-Softmax with s fixed at 1).
ATTENTION_SCALES = ("constant", "log_length")
# How a scratch model's cell words "(x, y)" start (pipeline.lm.models.build_scratch_model): drawn like every
# other row, or with a part linear in x and in y added, so that "x at most x1" can be one direction of the
# embedding that holds at any distance from the grid's corner.
COORDINATE_INITS = ("random", "linear")
# How the word-level tokenizer cuts a number outside a cell (pipeline.lm.tokenizer.NUMBER_PIECES): one piece, or
# one piece a digit.
NUMBERS = ("whole", "digits")
# Where the word-level tokenizer puts a newline (pipeline.lm.tokenizer.NEWLINE_PIECES): its own piece, or joined to
# the cell, word or punctuation mark that ends the line (the same text in about two thirds of the tokens); `composed`
# cuts as `joined` and ties each joined word's embedding to its word's plus a newline's
# (pipeline.lm.models.ComposedRows), so "(1, 2)\n" and "(1, 2)" share what is learnt of the cell.
NEWLINES = ("own", "joined", "composed")
# Where the word-level tokenizer puts a space before a cell (with `digits`, also before a digit: pipeline.lm.tokenizer.
# SPACE_PIECES): its own piece, or joined to the word or punctuation mark before it ("Step ", " at ", ": "): the
# same text in about 0.91x the tokens. Those few words are always followed by that space, so a joined word replaces
# its word instead of adding a second form of it (as a joined newline does). `phrases` joins further: each run of
# words, spaces and marks up to a cell, a digit, a line end or a full stop is one piece ("Grid is from ",
# " The wall is at ", "Thought:\n"): the same text in about 0.88x the tokens of `joined`.
SPACES = ("own", "joined", "phrases")


class ModelKind(str, Enum):
    scratch = "scratch"   # a small Llama built here, with the word-level tokenizer
    hf = "hf"             # a pretrained causal LM from a local directory


@dataclass
class ModelSettings:
    """The model: its kind and size (or where it is), its context, its chat format and prompt form.

    ``max_length`` is THE context length: a scratch model's positions, the longest conversation training
    keeps, and the bound decoding stays within. ``prompt`` is what the model is prompted with
    (`pipeline.core.texts.PROMPTS`): the paper's three turns, or the task turn alone (for models trained
    from scratch, which cannot use the fixed English instruction). The defaults are the base of every
    ``conf/model/*.yaml`` preset.
    """

    kind: ModelKind = ModelKind.scratch
    path: Optional[str] = None       # kind=hf: a local directory with a causal LM and its tokenizer
    hidden_size: int = 128
    num_layers: int = 4
    num_heads: int = 2
    intermediate_size: int = 512
    max_length: int = 2048
    dtype: str = "float32"
    attn_implementation: str = "sdpa"
    trust_remote_code: bool = False
    chat_format: ChatFormat = field(default_factory=ChatFormat)
    prompt: str = DEFAULT_PROMPT
    # How the answers' step headers are written (pipeline.core.texts.STEP_HEADERS): the paper's `Step k:`, or
    # `Step:` (plain: no number word that larger test worlds would need and training never shows).
    step_headers: str = field(default="numbered", metadata={"hash_if_set": True})
    # How an optimal answer's Plan is written (pipeline.core.texts.PLAN_FORMS): the paper's moves, or `anchored`
    # (each move after the cell it leaves, the goal last): a run of equal moves is then copied by its cells.
    plan_form: str = field(default="moves", metadata={"hash_if_set": True})
    # NUMBERS (scratch models): `digits` makes a step number larger than training shows of trained pieces.
    numbers: str = field(default="whole", metadata={"hash_if_set": True})
    newlines: str = field(default="own", metadata={"hash_if_set": True})   # NEWLINES; scratch models only
    spaces: str = field(default="own", metadata={"hash_if_set": True})   # SPACES; scratch models only
    positions: str = field(default="rope", metadata={"hash_if_set": True})   # POSITIONS; scratch models only
    attention_scale: str = field(default="constant", metadata={"hash_if_set": True})  # ATTENTION_SCALES; scratch
    coordinate_init: str = field(default="random", metadata={"hash_if_set": True})  # COORDINATE_INITS; scratch
    # RoPE's base (scratch models): 10000 is Llama's. A small base turns even the slowest rotary pair through
    # whole periods within the training lengths, so a longer test sequence meets no angle training never saw.
    rope_theta: float = field(default=10000.0, metadata={"hash_if_set": True})
    log_model: str = "transformers"

    def __post_init__(self) -> None:
        try:
            self.kind = ModelKind(self.kind.value if isinstance(self.kind, Enum) else self.kind)
        except ValueError:
            raise SettingError(f"kind={self.kind!r} is not allowed; expected one of scratch, hf") from None
        if isinstance(self.chat_format, dict):
            self.chat_format = ChatFormat(**self.chat_format)
        require(self.dtype in DTYPES, "dtype", self.dtype, f"one of {', '.join(DTYPES)}")
        require(self.attn_implementation in ATTENTION_IMPLEMENTATIONS, "attn_implementation",
                self.attn_implementation, f"one of {', '.join(ATTENTION_IMPLEMENTATIONS)}")
        require(self.prompt in PROMPTS, "prompt", self.prompt, f"one of {', '.join(PROMPTS)}")
        require(self.step_headers in STEP_HEADERS, "step_headers", self.step_headers, f"one of {', '.join(STEP_HEADERS)}")
        require(self.plan_form in PLAN_FORMS, "plan_form", self.plan_form, f"one of {', '.join(PLAN_FORMS)}")
        require(self.numbers in NUMBERS, "numbers", self.numbers, f"one of {', '.join(NUMBERS)}")
        require(self.newlines in NEWLINES, "newlines", self.newlines, f"one of {', '.join(NEWLINES)}")
        require(self.spaces in SPACES, "spaces", self.spaces, f"one of {', '.join(SPACES)}")
        require(self.positions in POSITIONS, "positions", self.positions, f"one of {', '.join(POSITIONS)}")
        require(self.attention_scale in ATTENTION_SCALES, "attention_scale", self.attention_scale,
                f"one of {', '.join(ATTENTION_SCALES)}")
        require(self.attention_scale == "constant" or self.kind is ModelKind.scratch, "attention_scale",
                self.attention_scale, "constant for a pretrained model (kind=hf keeps its own attention)")
        require(self.attention_scale == "constant" or self.attn_implementation == "sdpa", "attention_scale",
                self.attention_scale, f"constant with attn_implementation={self.attn_implementation} (log_length "
                "is built on sdpa)")
        require(self.coordinate_init in COORDINATE_INITS, "coordinate_init", self.coordinate_init,
                f"one of {', '.join(COORDINATE_INITS)}")
        require(self.coordinate_init == "random" or self.kind is ModelKind.scratch, "coordinate_init",
                self.coordinate_init, "random for a pretrained model (kind=hf keeps its own embeddings)")
        require(self.rope_theta > 1, "rope_theta", self.rope_theta, "a base above 1")
        require(self.numbers == "whole" or self.kind is ModelKind.scratch, "numbers", self.numbers,
                "whole for a pretrained model (kind=hf keeps its own tokenizer)")
        require(self.newlines == "own" or self.kind is ModelKind.scratch, "newlines", self.newlines,
                "own for a pretrained model (kind=hf keeps its own tokenizer)")
        require(self.spaces == "own" or self.kind is ModelKind.scratch, "spaces", self.spaces,
                "own for a pretrained model (kind=hf keeps its own tokenizer)")
        require(self.positions == "rope" or self.kind is ModelKind.scratch, "positions", self.positions,
                "rope for a pretrained model (kind=hf keeps its own position encoding)")
        require(self.log_model in LOG_MODEL_CHOICES, "log_model", self.log_model, f"one of {', '.join(LOG_MODEL_CHOICES)}")
        for name in ("hidden_size", "num_layers", "num_heads", "intermediate_size", "max_length"):
            value = getattr(self, name)
            require(isinstance(value, int) and value > 0, name, value, "a positive integer")
        require(self.hidden_size % self.num_heads == 0, "hidden_size", self.hidden_size,
                f"a multiple of num_heads={self.num_heads}")
        require(self.kind is ModelKind.scratch or bool(self.path), "path", self.path,
                "a local directory with a causal LM and its tokenizer (kind=hf needs one)")

    def to_dict(self) -> dict:
        """Plain JSON-ready values (the chat format as a dict, the kind as its string)."""
        values = {f.name: getattr(self, f.name) for f in fields(self)}
        return {**values, "kind": self.kind.value, "chat_format": asdict(self.chat_format)}
