"""Models and tokenizers: a small Llama built from scratch for CPU runs, or a pretrained one loaded from disk.

Loading is safetensors-only and never runs a model repository's own code unless asked, so a model directory
cannot execute anything by being opened. A directory that is missing or broken raises `ModelLoadError`
naming the path and what was expected, instead of a deep library traceback.
"""

from __future__ import annotations

import json
import logging
from dataclasses import asdict
from pathlib import Path
from typing import Iterable

import torch
from transformers import (
    AttentionInterface,
    AutoModelForCausalLM,
    AutoTokenizer,
    LlamaConfig,
    LlamaForCausalLM,
    PreTrainedModel,
    SmolLM3Config,
    SmolLM3ForCausalLM,
    PreTrainedTokenizerBase,
)
from transformers.integrations.sdpa_attention import sdpa_attention_forward
from transformers.masking_utils import AttentionMaskInterface, sdpa_mask

from pipeline.core.texts import parse_cell
from pipeline.lm.chat import ChatFormat
from pipeline.lm.model_settings import ATTENTION_IMPLEMENTATIONS, DTYPES, ModelKind, ModelSettings
from pipeline.lm.tokenizer import build_word_tokenizer

CHAT_FORMAT_FILE = "chat_format.json"
# The pad token the paper's training code adds to a tokenizer that has none (Meta-Llama-3-8B's has none).
PAD_TOKEN = "<pad>"

log = logging.getLogger(__name__)

# `ModelSettings.attention_scale=log_length`: the attention function such a model runs, registered with
# transformers' attention interfaces under this name (its masks are sdpa's). The model's config records the
# scale (`attention_scale`), and `load_model` picks this function for it.
LOG_LENGTH_ATTENTION = "sdpa_log_length"


def log_length_attention(module: torch.nn.Module, query: torch.Tensor, key: torch.Tensor, value: torch.Tensor,
                         attention_mask: torch.Tensor | None, *, position_ids: torch.Tensor | None = None,
                         **kwargs) -> tuple[torch.Tensor, None]:
    """sdpa attention whose logits are also multiplied by log(n), n = position + 1: the number of keys a
    causal query at that position sees. The largest logit then grows with the length, so a query can stay as
    sharply on one matching key among many as among few (Chiang and Cholak 2022; Scalable-Softmax, Nakanishi
    2025, there with a learnt factor s per head, fixed at 1 here so that the model keeps Llama's parameters)."""
    if position_ids is None:
        raise ValueError("log_length attention needs the position ids of the queries")
    scale = torch.log1p(position_ids.to(query.dtype))  # (batch or 1, queries)
    return sdpa_attention_forward(module, query * scale[:, None, :, None], key, value, attention_mask,
                                  position_ids=position_ids, **kwargs)


AttentionInterface.register(LOG_LENGTH_ATTENTION, log_length_attention)
AttentionMaskInterface.register(LOG_LENGTH_ATTENTION, sdpa_mask)


def make_tokenizer(settings: ModelSettings, texts: Iterable[str], frame: int) -> PreTrainedTokenizerBase:
    """The model's tokenizer: a word-level one over ``texts`` and the cells of ``frame`` (scratch), or the
    pretrained model's own, given a pad token if it has none (`with_pad_token`)."""
    if settings.kind is ModelKind.scratch:
        return build_word_tokenizer(texts, frame=frame, numbers=settings.numbers, newlines=settings.newlines,
                                    spaces=settings.spaces)
    return with_pad_token(load_tokenizer(settings.path, trust_remote_code=settings.trust_remote_code))


def with_pad_token(tokenizer: PreTrainedTokenizerBase) -> PreTrainedTokenizerBase:
    """``tokenizer`` with a pad token: if it has none, `PAD_TOKEN` added as a new special token, as the paper's
    training code does (the model's embeddings then grow by a row: `fit_embeddings`). Padding is never
    attended by a real token nor trained on, so any id would do; a new one keeps the paper's vocabulary."""
    if tokenizer.pad_token is None:
        tokenizer.add_special_tokens({"pad_token": PAD_TOKEN})
        log.info("the tokenizer has no pad token: added %s (id %d), as the paper's training code does",
                 PAD_TOKEN, tokenizer.pad_token_id)
    return tokenizer


def fit_embeddings(model: PreTrainedModel, tokenizer: PreTrainedTokenizerBase, *, seed: int = 0) -> PreTrainedModel:
    """``model`` with an embedding row (and output row) for every token of ``tokenizer``: rows for tokens
    the tokenizer added (its pad token) are drawn as transformers draws them (from the old rows' mean and
    covariance), seeded by ``seed``; the global torch RNG is left as it was. Sets the model's pad id."""
    rows = model.get_input_embeddings().num_embeddings
    if len(tokenizer) > rows:
        with torch.random.fork_rng(devices=[]):
            torch.manual_seed(seed)
            model.resize_token_embeddings(len(tokenizer))
        log.info("embeddings grown from %d to %d rows for the tokens the tokenizer added", rows, len(tokenizer))
    model.config.pad_token_id = tokenizer.pad_token_id
    return model


def make_model(settings: ModelSettings, tokenizer: PreTrainedTokenizerBase, *, seed: int = 0) -> PreTrainedModel:
    """THE place a model to train comes from: a new Llama sized by ``settings`` (scratch, seeded), or the
    pretrained one at ``settings.path`` with rows for the tokens its tokenizer added (`fit_embeddings`)."""
    if settings.kind is ModelKind.scratch:
        return build_scratch_model(tokenizer, settings, seed=seed)
    model = load_model(settings.path, dtype=settings.dtype, trust_remote_code=settings.trust_remote_code,
                       attn_implementation=settings.attn_implementation)
    return fit_embeddings(model, tokenizer, seed=seed)


_EXPECTED_MODEL = "a local transformers model directory with config.json and *.safetensors weights"
_EXPECTED_TOKENIZER = "a local tokenizer directory (tokenizer.json or the files of a saved tokenizer)"


class ModelLoadError(ValueError):
    """A model or tokenizer directory that is missing, incomplete or unreadable."""


def build_scratch_model(tokenizer: PreTrainedTokenizerBase, settings: ModelSettings, *, seed: int = 0
                        ) -> PreTrainedModel:
    """A randomly initialised fp32 Llama sized by ``settings`` for ``tokenizer``; the same seed gives the same
    weights (`make_model` is the entry point; this is its scratch half).

    ``settings.positions`` (`POSITIONS`): ``rope`` builds a Llama; ``nope`` and ``alternate`` build the same
    network as transformers' SmolLM3 (a Llama whose layers each switch RoPE on or off), with RoPE in no layer or
    in layers 0, 2, ...; ``settings.rope_theta`` is RoPE's base. ``settings.attention_scale=log_length`` runs
    `log_length_attention` and records it in the config. ``settings.coordinate_init=linear`` starts the cell
    words' embeddings with `linear_coordinates`. The global torch RNG is left as it was, so
    building a model does not shift later draws.
    """
    s = settings
    config_class, extra = LlamaConfig, {}
    if s.positions != "rope":
        # SmolLM3's no_rope_layers: 1 = this layer uses RoPE, 0 = it does not.
        uses_rope = [int(s.positions == "alternate" and layer % 2 == 0) for layer in range(s.num_layers)]
        config_class, extra = SmolLM3Config, {"no_rope_layers": uses_rope, "use_sliding_window": False}
    attn_implementation = s.attn_implementation
    if s.attention_scale != "constant":
        extra["attention_scale"] = s.attention_scale
        attn_implementation = LOG_LENGTH_ATTENTION
    config = config_class(
        vocab_size=len(tokenizer),
        hidden_size=s.hidden_size,
        num_hidden_layers=s.num_layers,
        num_attention_heads=s.num_heads,
        num_key_value_heads=s.num_heads,
        intermediate_size=s.intermediate_size,
        max_position_embeddings=s.max_length,
        pad_token_id=tokenizer.pad_token_id,
        bos_token_id=tokenizer.bos_token_id,
        eos_token_id=tokenizer.eos_token_id,
        tie_word_embeddings=True,
        attn_implementation=attn_implementation,
        rope_theta=s.rope_theta,
        **extra,
    )
    if s.newlines == "composed":
        config.composed_newlines = True   # the trainer keeps the joined rows composed (`ComposedRows`)
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        model = (LlamaForCausalLM if s.positions == "rope" else SmolLM3ForCausalLM)(config)
        if s.coordinate_init == "linear":
            linear_coordinates(model, tokenizer)
    model = model.to(torch.float32)
    if s.newlines == "composed":
        ComposedRows.of(tokenizer).compose(model.get_input_embeddings().weight)
    return model


class ComposedRows:
    """The embedding rows of a `composed` word-level vocabulary (``model.newlines=composed``): the row of every
    joined word ("(1, 2)\\n", "up\\n") is its word's row plus the newline's, in the input embedding and (tied)
    the output head, so what training learns of a cell from either form serves both. The rows stay a plain
    embedding matrix (a saved model is a plain Llama): `compose` writes the joined rows from the others, and
    `gradient` (a hook on the weight) moves each joined row's gradient to its two parts, which is the gradient
    of the composed parametrisation. Composing twice is composing once, so a checkpoint resumes exactly. A
    joined word whose word alone is not in the vocabulary ("cut\\n") keeps a row of its own."""

    def __init__(self, joined: list[int], words: list[int], newline: int):
        self.joined, self.words, self.newline = torch.tensor(joined), torch.tensor(words), newline

    @classmethod
    def of(cls, tokenizer: PreTrainedTokenizerBase) -> "ComposedRows":
        vocab = tokenizer.get_vocab()
        if "\n" not in vocab:
            raise ValueError("newlines=composed needs a newline token in the vocabulary (build_word_tokenizer "
                             "with newlines='composed' adds one)")
        pairs = sorted((index, vocab[word[:-1]]) for word, index in vocab.items()
                       if len(word) > 1 and word.endswith("\n") and word[:-1] in vocab)
        return cls([j for j, _ in pairs], [w for _, w in pairs], vocab["\n"])

    @torch.no_grad()
    def compose(self, weight: torch.Tensor) -> None:
        weight[self.joined] = weight[self.words] + weight[self.newline]

    def gradient(self, grad: torch.Tensor) -> torch.Tensor:
        joined = grad[self.joined]
        grad = grad.index_add(0, self.words, joined)
        grad[self.newline] += joined.sum(0)
        grad[self.joined] = 0
        return grad


@torch.no_grad()
def linear_coordinates(model: PreTrainedModel, tokenizer: PreTrainedTokenizerBase) -> None:
    """Add x * a + y * b to the embedding row of every cell word "(x, y)" of ``tokenizer`` (a and b: two rows
    drawn like the others, from the global RNG), so that the cells start on a plane: a cell's x is one
    direction of its embedding, and comparing it with a bound's is the same at any distance. The rest of each
    row stays its own, so that equal cells still match and neighbours still differ; training moves both."""
    weight = model.get_input_embeddings().weight
    std = model.config.initializer_range
    a, b = torch.randn(2, weight.shape[1]) * std
    for word, index in tokenizer.get_vocab().items():
        cell = parse_cell(word.removesuffix("\n"))   # with newlines joined, "(x, y)\n" is the same cell
        if cell is not None:
            weight[index] += cell[0] * a + cell[1] * b


def _torch_dtype(dtype: str) -> torch.dtype:
    if dtype not in DTYPES:
        raise ValueError(f"dtype={dtype!r} is not supported; allowed: {', '.join(DTYPES)}")
    return getattr(torch, dtype)


def _check_attention(attn_implementation: str | None) -> None:
    if attn_implementation is not None and attn_implementation not in ATTENTION_IMPLEMENTATIONS:
        raise ValueError(f"attn_implementation={attn_implementation!r} is not supported; "
                         f"allowed: {', '.join(ATTENTION_IMPLEMENTATIONS)}")


def _require_dir(path: Path, expected: str) -> None:
    if not path.is_dir():
        raise ModelLoadError(f"{path}: no such directory; expected {expected}")


def load_model(path: str | Path, *, dtype: str = "float32", trust_remote_code: bool = False,
               attn_implementation: str | None = None) -> PreTrainedModel:
    """A causal LM from a local directory of safetensors weights (no pickle, no remote code unless asked).
    ``attn_implementation`` None keeps transformers' choice for the model; a model whose config records
    ``attention_scale: log_length`` runs `log_length_attention` (its math, not a kernel choice)."""
    torch_dtype = _torch_dtype(dtype)
    _check_attention(attn_implementation)
    path = Path(path)
    _require_dir(path, _EXPECTED_MODEL)
    if not (path / "config.json").is_file():
        raise ModelLoadError(f"{path}: config.json is missing; expected {_EXPECTED_MODEL}")
    if attention_scale(path) == "log_length":
        if attn_implementation not in (None, "sdpa"):
            raise ValueError(f"attn_implementation={attn_implementation!r} is not allowed for {path}: its model "
                             "scales attention by log_length, which runs on sdpa only")
        attn_implementation = LOG_LENGTH_ATTENTION
    extra = {} if attn_implementation is None else {"attn_implementation": attn_implementation}
    if not any(path.glob("*.safetensors")):
        raise ModelLoadError(f"{path}: no *.safetensors file; expected {_EXPECTED_MODEL}")
    try:
        return AutoModelForCausalLM.from_pretrained(
            path, dtype=torch_dtype, use_safetensors=True, trust_remote_code=trust_remote_code,
            local_files_only=True, **extra,
        )
    except Exception as exc:  # safetensors, json and torch each raise their own types for a broken file
        raise ModelLoadError(f"{path}: cannot load the model ({type(exc).__name__}: {exc}); "
                             f"expected {_EXPECTED_MODEL}") from exc


def attention_scale(model_dir: str | Path) -> str:
    """How the model saved in ``model_dir`` scales its attention logits (`ATTENTION_SCALES`; a model without
    the record, pretrained ones included: ``constant``)."""
    try:
        config = json.loads((Path(model_dir) / "config.json").read_text())
    except (OSError, ValueError) as exc:
        raise ModelLoadError(f"{model_dir}: cannot read config.json ({exc}); expected {_EXPECTED_MODEL}") from exc
    return config.get("attention_scale", "constant") if isinstance(config, dict) else "constant"


def load_tokenizer(path: str | Path, *, trust_remote_code: bool = False) -> PreTrainedTokenizerBase:
    """A tokenizer saved with ``save_pretrained`` in a local directory."""
    path = Path(path)
    _require_dir(path, _EXPECTED_TOKENIZER)
    try:
        return AutoTokenizer.from_pretrained(path, trust_remote_code=trust_remote_code, local_files_only=True)
    except Exception as exc:
        raise ModelLoadError(f"{path}: cannot load the tokenizer ({type(exc).__name__}: {exc}); "
                             f"expected {_EXPECTED_TOKENIZER}") from exc


def save_chat_format(fmt: ChatFormat, model_dir: str | Path) -> Path:
    """Write the chat format next to a saved model, so a decoder encodes prompts as training did."""
    target = Path(model_dir) / CHAT_FORMAT_FILE
    target.write_text(json.dumps(asdict(fmt), indent=2) + "\n")
    return target


def load_chat_format(model_dir: str | Path) -> ChatFormat:
    """The chat format saved with a model by `save_chat_format`."""
    source = Path(model_dir) / CHAT_FORMAT_FILE
    if not source.is_file():
        raise ModelLoadError(f"{model_dir}: {CHAT_FORMAT_FILE} is missing; expected a model saved by finetune")
    return ChatFormat(**json.loads(source.read_text()))
