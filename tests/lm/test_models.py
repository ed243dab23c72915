import pytest
import torch

from pipeline.lm.chat import WORD_LEVEL_FORMAT, ChatFormat
from pipeline.lm.model_settings import ModelSettings
from pipeline.lm.models import (
    PAD_TOKEN,
    ComposedRows,
    ModelLoadError,
    LOG_LENGTH_ATTENTION,
    attention_scale,
    build_scratch_model,
    log_length_attention,
    make_model,
    make_tokenizer,
    load_chat_format,
    load_model,
    load_tokenizer,
    save_chat_format,
)
from pipeline.lm.tokenizer import build_word_tokenizer

TINY = dict(hidden_size=32, num_layers=2, num_heads=2, intermediate_size=64, max_length=256)


def _scratch(tokenizer, seed=0, **changes):
    return build_scratch_model(tokenizer, ModelSettings(**{**TINY, **changes}), seed=seed)


@pytest.fixture(scope="module")
def tokenizer():
    return build_word_tokenizer(["Grid is from (0, 0) to (3, 2). Goal: (3, 2)\nThought:\nStep 1:\nup\nPlan:"])


def test_scratch_model_is_sized_for_the_tokenizer(tokenizer):
    model = _scratch(tokenizer)
    assert model.config.vocab_size == len(tokenizer)
    assert (model.config.pad_token_id, model.config.bos_token_id, model.config.eos_token_id) == (
        tokenizer.pad_token_id, tokenizer.bos_token_id, tokenizer.eos_token_id)
    assert model.dtype == torch.float32
    assert model.config._attn_implementation == "sdpa"


def test_scratch_model_is_deterministic_and_keeps_the_global_rng(tokenizer):
    state = torch.random.get_rng_state()
    a = _scratch(tokenizer, seed=1)
    assert torch.equal(torch.random.get_rng_state(), state)
    b = _scratch(tokenizer, seed=1)
    c = _scratch(tokenizer, seed=2)
    assert all(torch.equal(x, y) for x, y in zip(a.parameters(), b.parameters()))
    assert not torch.equal(a.model.layers[0].mlp.up_proj.weight, c.model.layers[0].mlp.up_proj.weight)


def test_heads_must_divide_hidden(tokenizer):
    with pytest.raises(ValueError, match="num_heads"):
        _scratch(tokenizer, hidden_size=30, num_heads=4)


@torch.no_grad()
def test_eager_and_sdpa_attention_agree_and_unknown_kernels_are_refused(tokenizer, tmp_path):
    sdpa = _scratch(tokenizer).eval()
    eager = _scratch(tokenizer, attn_implementation="eager").eval()
    ids = torch.tensor([tokenizer.encode("Grid is from (0, 0) to (3, 2).", add_special_tokens=False)])
    torch.testing.assert_close(sdpa(input_ids=ids).logits, eager(input_ids=ids).logits, atol=1e-5, rtol=1e-5)
    with pytest.raises(ValueError, match="attn_implementation='flash' is not allowed; expected one of sdpa, eager"):
        _scratch(tokenizer, attn_implementation="flash")
    sdpa.save_pretrained(tmp_path)
    assert load_model(tmp_path, attn_implementation="eager").config._attn_implementation == "eager"
    with pytest.raises(ValueError, match="attn_implementation='flash'"):
        load_model(tmp_path, attn_implementation="flash")


def test_save_and_load_round_trip(tokenizer, tmp_path):
    model = _scratch(tokenizer)
    model.save_pretrained(tmp_path)
    tokenizer.save_pretrained(tmp_path)
    loaded, loaded_tok = load_model(tmp_path), load_tokenizer(tmp_path)
    assert all(torch.equal(x, y) for x, y in zip(model.state_dict().values(), loaded.state_dict().values()))
    text = "Grid is from (0, 0) to (3, 2)."
    assert loaded_tok.encode(text, add_special_tokens=False) == tokenizer.encode(text, add_special_tokens=False)
    assert loaded_tok.pad_token_id == tokenizer.pad_token_id


def test_missing_model_dir_names_the_path(tmp_path):
    missing = tmp_path / "nowhere"
    with pytest.raises(ModelLoadError, match="nowhere.*no such directory.*safetensors"):
        load_model(missing)
    with pytest.raises(ModelLoadError, match="nowhere"):
        load_tokenizer(missing)


def test_dir_without_weights_is_refused(tokenizer, tmp_path):
    _scratch(tokenizer).config.save_pretrained(tmp_path)
    with pytest.raises(ModelLoadError, match="no \\*.safetensors"):
        load_model(tmp_path)


@pytest.mark.parametrize("damage", ["truncate", "garbage"])
def test_corrupt_safetensors_is_a_model_load_error(tokenizer, tmp_path, damage):
    _scratch(tokenizer).save_pretrained(tmp_path)
    weights = tmp_path / "model.safetensors"
    data = weights.read_bytes()
    weights.write_bytes(data[: len(data) // 2] if damage == "truncate" else b"\x00garbage" * 64)
    with pytest.raises(ModelLoadError, match=str(tmp_path)):
        load_model(tmp_path)


def test_unknown_dtype_is_refused(tmp_path):
    with pytest.raises(ValueError, match="float64.*allowed: float32"):
        load_model(tmp_path, dtype="float64")


def test_chat_format_round_trip(tmp_path):
    fmt = ChatFormat(human_prefix="<|user|>", gpt_prefix="<|assistant|>", turn_end="<|eot|>", bos="")
    save_chat_format(fmt, tmp_path)
    assert load_chat_format(tmp_path) == fmt
    save_chat_format(WORD_LEVEL_FORMAT, tmp_path)
    assert load_chat_format(tmp_path) == WORD_LEVEL_FORMAT




@pytest.mark.parametrize(("positions", "uses_rope"), [("nope", [0, 0]), ("alternate", [1, 0])])
@torch.no_grad()
def test_positions_switch_rope_per_layer_and_round_trip(tokenizer, tmp_path, positions, uses_rope):
    """`nope`/`alternate` build the same network with RoPE off in some layers: the Llama's parameters, other
    outputs; position ids reach only the RoPE layers (stretched positions change the alternate model, not the
    NoPE one); saved and loaded through the Auto classes."""
    rope = _scratch(tokenizer, seed=1).eval()
    model = _scratch(tokenizer, seed=1, positions=positions).eval()
    assert model.config.no_rope_layers == uses_rope
    assert [n for n, _ in model.named_parameters()] == [n for n, _ in rope.named_parameters()]
    assert all(torch.equal(a, b) for a, b in zip(model.parameters(), rope.parameters()))
    ids = torch.tensor([tokenizer.encode("Grid is from (0, 0) to (3, 2).", add_special_tokens=False)])
    assert not torch.allclose(model(input_ids=ids).logits, rope(input_ids=ids).logits)
    stretched = model(input_ids=ids, position_ids=torch.arange(ids.shape[1])[None] * 3).logits
    assert torch.allclose(stretched, model(input_ids=ids).logits, atol=1e-6) == (positions == "nope")
    model.save_pretrained(tmp_path)
    loaded = load_model(tmp_path)
    assert type(loaded) is type(model) and loaded.config.no_rope_layers == uses_rope
    torch.testing.assert_close(loaded(input_ids=ids).logits, model(input_ids=ids).logits)
    with pytest.raises(ValueError, match="positions='alibi' is not allowed; expected one of rope, nope, alternate"):
        _scratch(tokenizer, positions="alibi")


def test_log_length_attention_scales_each_querys_logits_by_the_log_of_the_keys_it_sees():
    """Against softmax written out: logits q.k / sqrt(d) * log(position + 1), causal."""
    g = torch.Generator().manual_seed(0)
    q, k, v = (torch.randn(1, 2, 5, 4, generator=g) for _ in range(3))
    positions = torch.arange(5)[None]
    module = torch.nn.Module()
    module.is_causal = True
    out, _ = log_length_attention(module, q, k, v, None, position_ids=positions, scaling=0.5, dropout=0.0)
    logits = (q @ k.mT) * 0.5 * torch.log(positions + 1.0)[:, None, :, None]
    logits = logits.masked_fill(torch.ones(5, 5, dtype=torch.bool).triu(1), float("-inf"))
    torch.testing.assert_close(out, (logits.softmax(-1) @ v).transpose(1, 2))
    with pytest.raises(ValueError, match="needs the position ids"):
        log_length_attention(module, q, k, v, None, scaling=0.5)


@torch.no_grad()
def test_attention_scale_switch_keeps_the_parameters_changes_the_outputs_and_round_trips(tokenizer, tmp_path):
    """`attention_scale=log_length`: Llama's parameters, other outputs; recorded in the config, so the loaded
    model runs it too; cached decoding (one token at a time) sees the same positions as a whole forward."""
    plain = _scratch(tokenizer, seed=1).eval()
    model = _scratch(tokenizer, seed=1, attention_scale="log_length").eval()
    assert model.config._attn_implementation == LOG_LENGTH_ATTENTION and model.config.attention_scale == "log_length"
    assert all(torch.equal(a, b) for a, b in zip(model.parameters(), plain.parameters()))
    ids = torch.tensor([tokenizer.encode("Grid is from (0, 0) to (3, 2). Goal: (3, 2)", add_special_tokens=False)])
    whole = model(input_ids=ids).logits
    assert not torch.allclose(whole, plain(input_ids=ids).logits)
    prefix = model(input_ids=ids[:, :-1], use_cache=True)
    step = model(input_ids=ids[:, -1:], cache=prefix.past_key_values).logits
    torch.testing.assert_close(step[:, -1], whole[:, -1], rtol=1e-4, atol=1e-5)
    model.save_pretrained(tmp_path)
    assert attention_scale(tmp_path) == "log_length"
    loaded = load_model(tmp_path)
    assert loaded.config._attn_implementation == LOG_LENGTH_ATTENTION
    torch.testing.assert_close(loaded(input_ids=ids).logits, whole)
    with pytest.raises(ValueError, match="attn_implementation='eager' is not allowed.*log_length"):
        load_model(tmp_path, attn_implementation="eager")
    plain.save_pretrained(tmp_path / "plain")
    assert attention_scale(tmp_path / "plain") == "constant"


@pytest.mark.parametrize(("changes", "message"), [
    (dict(attention_scale="alibi"), "attention_scale='alibi' is not allowed; expected one of constant, log_length"),
    (dict(attention_scale="log_length", attn_implementation="eager"), "constant with attn_implementation=eager"),
    (dict(attention_scale="log_length", kind="hf", path="x"), "constant for a pretrained model"),
])
def test_attention_scale_names_what_is_allowed(changes, message):
    with pytest.raises(ValueError, match=message):
        ModelSettings(**changes)


@torch.no_grad()
@pytest.mark.parametrize("newlines", ["own", "joined"])
def test_linear_coordinate_init_adds_a_plane_to_the_cell_words_alone(newlines):
    """`coordinate_init=linear`: the same model but for the cell words' rows, each moved by x * a + y * b (with
    newlines joined, "(x, y)" and "(x, y)\n" alike)."""
    tokenizer = build_word_tokenizer(["Grid is from (0, 0) to (3, 2). Goal: (3, 2)\nup"], frame=4, newlines=newlines)
    state = torch.random.get_rng_state()
    plain = _scratch(tokenizer, seed=2).get_input_embeddings().weight
    linear = _scratch(tokenizer, seed=2, coordinate_init="linear").get_input_embeddings().weight
    assert torch.equal(torch.random.get_rng_state(), state)
    vocab = tokenizer.get_vocab()
    shift = {word: linear[i] - plain[i] for word, i in vocab.items()}
    cells = [word for word in vocab if word.startswith("(")]
    assert len(cells) == 36 * (1 + (newlines == "joined")) and all(not shift[word].any() for word in vocab
                                                                   if word not in cells)
    a, b = shift["(1, 0)"] - shift["(0, 0)"], shift["(0, 1)"] - shift["(0, 0)"]
    assert a.norm() > 0 and b.norm() > 0 and not torch.allclose(a, b)
    for word in cells:
        x, y = (int(v) for v in word.removesuffix("\n")[1:-1].split(", "))
        torch.testing.assert_close(shift[word], x * a + y * b, rtol=1e-4, atol=1e-5)
    with pytest.raises(ValueError, match="coordinate_init='grid' is not allowed; expected one of random, linear"):
        ModelSettings(coordinate_init="grid")
    with pytest.raises(ValueError, match="random for a pretrained model"):
        ModelSettings(kind="hf", path="x", coordinate_init="linear")


def test_a_tokenizer_without_a_pad_token_gets_the_papers_and_the_model_a_row_for_it(tiny_llama3_dir, tokenizer, tmp_path):
    # Meta-Llama-3-8B's tokenizer has no pad token: the collator was built with None and training crashed.
    # The paper's code adds "<pad>" as a new special token and grows the embeddings to the tokenizer's size.
    settings = ModelSettings(kind="hf", path=str(tiny_llama3_dir))
    assert load_tokenizer(tiny_llama3_dir).pad_token is None
    tokenizer = make_tokenizer(settings, [], frame=0)
    assert (tokenizer.pad_token, tokenizer.pad_token_id, len(tokenizer)) == (PAD_TOKEN, 128256, 128257)
    state = torch.random.get_rng_state()
    model = make_model(settings, tokenizer, seed=3)
    assert torch.equal(torch.random.get_rng_state(), state)
    assert model.get_input_embeddings().num_embeddings == model.get_output_embeddings().out_features == 128257
    assert model.config.pad_token_id == 128256
    # The new row is drawn from the seed: the same seed, the same row; the old rows are untouched.
    again, other = make_model(settings, tokenizer, seed=3), make_model(settings, tokenizer, seed=4)
    rows = [m.get_input_embeddings().weight for m in (model, again, other)]
    assert torch.equal(rows[0], rows[1]) and not torch.equal(rows[0][-1], rows[2][-1])
    assert torch.equal(rows[0][:-1], load_model(tiny_llama3_dir).get_input_embeddings().weight)
    # A tokenizer that has a pad token keeps it, and its model keeps its size.
    _scratch(tokenizer).save_pretrained(tmp_path)
    tokenizer.save_pretrained(tmp_path)
    padded = ModelSettings(kind="hf", path=str(tmp_path))
    assert make_tokenizer(padded, [], frame=0).pad_token_id == tokenizer.pad_token_id
    assert make_model(padded, make_tokenizer(padded, [], frame=0)).config.vocab_size == len(tokenizer)


def test_composed_newlines_tie_each_joined_row_to_its_word_and_the_newline():
    """newlines=composed: "(1, 2)\n" is "(1, 2)" plus "\n", input and (tied) output alike; a joined word without
    its word alone ("cut\n") keeps a row of its own; the rest is the joined model's draw."""
    text = "Grid is from (0, 0) to (3, 2). Goal: (3, 2)\nThought:\n(1, 2)\ncut\nup\nup right\nPlan:"
    composed_tokenizer = build_word_tokenizer([text], frame=4, newlines="composed")
    vocab = composed_tokenizer.get_vocab()
    assert "\n" in vocab and "\n" not in build_word_tokenizer([text], frame=4, newlines="joined").get_vocab()
    model = _scratch(composed_tokenizer, newlines="composed")
    assert model.config.composed_newlines and model.get_output_embeddings().weight is model.get_input_embeddings().weight
    weight = model.get_input_embeddings().weight
    for word in ("(1, 2)", "(-1, 4)", "up", ":"):
        torch.testing.assert_close(weight[vocab[word + "\n"]], weight[vocab[word]] + weight[vocab["\n"]])
    rows = ComposedRows.of(composed_tokenizer)
    joined = {word for word, index in vocab.items() if index in rows.joined.tolist()}
    assert joined == {word for word in vocab if word.startswith("(") and word.endswith("\n")} | {"up\n", ":\n"}
    assert len(joined) == 36 + 2 and {"cut\n", " right\n"} <= set(vocab)   # "cut", " right": only at a line end
    with pytest.raises(ValueError, match="needs a newline token"):
        ComposedRows.of(build_word_tokenizer([text], frame=4, newlines="joined"))


def test_composed_rows_gradient_is_the_gradient_of_the_composition():
    """The hook's gradient on the plain weight equals autograd's through an explicit composition of free rows."""
    tokenizer = build_word_tokenizer(["Goal: (3, 2)\nThought:\n(1, 2)\nup\n(2, 2)\nPlan:\nup"], frame=4,
                                     newlines="composed")
    model = _scratch(tokenizer, seed=3, newlines="composed")
    rows = ComposedRows.of(tokenizer)
    ids = tokenizer("Goal: (3, 2)\nThought:\n(1, 2)\nup\n(2, 2)\nPlan:\nup", return_tensors="pt")["input_ids"]
    weight = model.get_input_embeddings().weight
    hook = weight.register_hook(rows.gradient)
    model(input_ids=ids, labels=ids).loss.backward()
    hook.remove()
    hooked = weight.grad.clone()

    free = weight.detach().clone().requires_grad_()
    composed = free.index_put((rows.joined,), free[rows.words] + free[rows.newline])
    names = ("model.embed_tokens.weight", "lm_head.weight")
    loss = torch.func.functional_call(model, {name: composed for name in names}, (),
                                      {"input_ids": ids, "labels": ids}, tie_weights=False).loss
    loss.backward()
    torch.testing.assert_close(hooked, free.grad)
    assert hooked[rows.joined].abs().sum() == 0 and hooked[rows.newline].abs().sum() > 0
