"""The word-level tokenizer: exact round trips, coordinates as single words, full frame coverage."""

from hypothesis import given, settings
from hypothesis import strategies as st

from fastchat_reference import render_conversation
from pipeline.lm.chat import WORD_LEVEL_FORMAT, encode_conversation, encode_conversations
from pipeline.core.generators import GeneratorConfig, generate_worlds
from pipeline.core.texts import conversation
from pipeline.lm.tokenizer import (
    SPECIAL_TOKENS, build_word_tokenizer, coverage_text, piece_census, pieces, word_level_encoder,
)

WORLDS = generate_worlds(30, 0, GeneratorConfig(size_x=(2, 5), size_y=(2, 5), frame=8))
TEXTS = [turn["value"] for w in WORLDS for turn in conversation(w, "fwd", "marking-deadend", "reachable")]
TOKENIZER = build_word_tokenizer(TEXTS, frame=8)


def test_coordinates_are_single_pieces_and_counts_agree():
    text = "Current:\n(3, -1)\nPossible:\n(0, 1)\nup. The wall is at (1, 1), and (2, 2)."
    assert pieces(text)[:4] == ["Current", ":", "\n", "(3, -1)"]
    assert "(1, 1)" in pieces(text) and "(2, 2)" in pieces(text)
    assert piece_census(text)[0] == len(pieces(text)) == len(TOKENIZER.encode(text, add_special_tokens=False))
    assert piece_census(text)[1] == set(pieces(text))


def test_digits_cut_a_number_into_its_digits_with_the_space_apart():
    text = "Step 12:\n(3, 4)\nup\nStep 7:"
    assert pieces(text, "digits") == ["Step", " ", "1", "2", ":", "\n", "(3, 4)", "\n", "up", "\n", "Step", " ",
                                      "7", ":"]
    assert pieces(text)[:3] == ["Step", " 12", ":"]
    tokenizer = build_word_tokenizer(TEXTS, frame=8, numbers="digits")
    # A number no text holds is known by its digits; every text round-trips.
    ids = tokenizer.encode("Step 98:", add_special_tokens=False)
    assert tokenizer.unk_token_id not in ids and tokenizer.decode(ids) == "Step 98:"
    for text in TEXTS[:50]:
        ids = tokenizer.encode(text, add_special_tokens=False)
        assert tokenizer.decode(ids) == text and len(ids) == piece_census(text, "digits")[0]


def test_joined_newlines_end_a_line_with_its_last_piece_and_keep_every_text():
    text = "Thought:\nStep 12:\n(3, 4)\ncut\n(0, 2)\nup\n\nPlan:\n(0, 1). The wall is at (1, 1)"
    assert pieces(text, "digits", "joined") == ["Thought", ":\n", "Step", " ", "1", "2", ":\n", "(3, 4)\n", "cut\n",
                                                "(0, 2)\n", "up\n", "\n", "Plan", ":\n", "(0, 1)", ".", " The",
                                                " wall", " is", " at", " ", "(1, 1)"]
    tokenizer = build_word_tokenizer(TEXTS, frame=8, numbers="digits", newlines="joined")
    joined = own = 0
    for text in TEXTS:
        ids = tokenizer.encode(text, add_special_tokens=False)
        assert tokenizer.unk_token_id not in ids and tokenizer.decode(ids) == text
        assert len(ids) == piece_census(text, "digits", "joined")[0]
        joined, own = joined + len(ids), own + piece_census(text, "digits")[0]
    assert joined < 0.8 * own   # the same texts in fewer tokens
    # Both words of every frame cell are known, the one that ends a line too, even where no text has it.
    for cell in ("(8, -1)", "(-1, 8)", "(7, 7)"):
        for word in (cell, cell + "\n"):
            assert tokenizer.convert_tokens_to_ids(word) != tokenizer.unk_token_id
    # The default cut is unchanged by the switch's existence: a newline is its own token.
    assert build_word_tokenizer(TEXTS, frame=8, newlines="own").get_vocab() == TOKENIZER.get_vocab()
    assert "(3, 4)\n" not in TOKENIZER.get_vocab()


def _round_trips(spaces: str, against: str):
    """The default's cut with ``spaces``, built on TEXTS: each text decodes back to itself, with no unknown token, in
    as many tokens as its census counts. Returns the tokenizer, the texts' tokens, and theirs with ``against``."""
    tokenizer = build_word_tokenizer(TEXTS, frame=8, numbers="digits", newlines="composed", spaces=spaces)
    tokens = theirs = 0
    for text in TEXTS:
        ids = tokenizer.encode(text, add_special_tokens=False)
        assert tokenizer.unk_token_id not in ids and tokenizer.decode(ids) == text
        assert len(ids) == piece_census(text, "digits", "composed", spaces)[0]
        tokens, theirs = tokens + len(ids), theirs + piece_census(text, "digits", "composed", against)[0]
    return tokenizer, tokens, theirs


def test_joined_spaces_end_the_word_before_a_cell_or_digit_and_keep_every_text():
    text = "Grid is from (1, 2) to (2, 5). Goal: (2, 5)\nThe wall is at (1, 1), (2, 2), and (3, 3).\nStep 12:\nup"
    assert pieces(text, "digits", "composed", "joined") == [
        "Grid", " is", " from ", "(1, 2)", " to ", "(2, 5)", ".", " Goal", ": ", "(2, 5)\n", "The", " wall", " is",
        " at ", "(1, 1)", ", ", "(2, 2)", ",", " and ", "(3, 3)", ".\n", "Step ", "1", "2", ":\n", "up"]
    # A whole number keeps its own leading space; any other space stays where it was.
    assert pieces("Step 12: at (1, 1)  (2, 2) x", "whole", "own", "joined") == [
        "Step", " 12", ":", " at ", "(1, 1)", " ", " ", "(2, 2)", " x"]
    tokenizer, joined, own = _round_trips(spaces="joined", against="own")
    assert joined < 0.95 * own   # the same texts in fewer tokens
    ids = tokenizer.encode("Step 98:\n", add_special_tokens=False)   # a step number no text holds
    assert tokenizer.unk_token_id not in ids and tokenizer.decode(ids) == "Step 98:\n"
    # The default cut is unchanged by the switch's existence.
    assert build_word_tokenizer(TEXTS, frame=8, spaces="own").get_vocab() == TOKENIZER.get_vocab()


def test_phrases_make_each_run_of_words_and_marks_one_piece_and_keep_every_text():
    text = ("Grid is from (1, 2) to (2, 5). Goal: (2, 5)\nThere is no pit. There is no wall.\n"
            "The wall is at (1, 1), (2, 2), and (3, 3).\nStep 12:\nup")
    assert pieces(text, "digits", "composed", "phrases") == [
        "Grid is from ", "(1, 2)", " to ", "(2, 5)", ".", " Goal: ", "(2, 5)\n", "There is no pit.",
        " There is no wall.\n", "The wall is at ", "(1, 1)", ", ", "(2, 2)", ", and ", "(3, 3)", ".\n", "Step ", "1",
        "2", ":\n", "up"]
    # A full stop ends its sentence's piece, a line end its line's; a newline of its own, a number whole.
    assert pieces("Step 12: at (1, 1)  (2, 2) x. y\n(z", "whole", "own", "phrases") == [
        "Step ", "12", ": at ", "(1, 1)", "  ", "(2, 2)", " x.", " y", "\n", "(", "z"]
    tokenizer, phrases, joined = _round_trips(spaces="phrases", against="joined")
    assert phrases < 0.95 * joined   # the same texts in fewer tokens again
    assert "\n" in tokenizer.get_vocab()   # the newline row a composed word adds to its word's, as with any cut
    # A line no training text holds, made of trained pieces: a world without pits or walls, a step number.
    ids = tokenizer.encode("There is no pit. There is no wall.\nStep 98:\n", add_special_tokens=False)
    assert tokenizer.unk_token_id not in ids
    assert tokenizer.decode(ids) == "There is no pit. There is no wall.\nStep 98:\n"


def test_the_vocabulary_is_the_pre_tokenizers_pieces_of_any_text():
    # Plain texts take Python's regex, others the tokenizer's own pre-tokenizer: both give its pieces.
    texts = [*TEXTS[:40], "h\u00e9llo (1, 2)\u00a0x\x1c y\u0663 12", "tab\there\r\nz", "   ", "",
             "at (1, 2) at\u00a0(1, 2) Step 3 Step\u00a04: \u0663 (2, 2)\n"]
    for numbers, newlines, spaces in (("whole", "own", "own"), ("digits", "composed", "own"),
                                      ("whole", "own", "joined"), ("digits", "composed", "joined"),
                                      ("whole", "own", "phrases"), ("digits", "composed", "phrases")):
        tokenizer = build_word_tokenizer(texts, frame=8, numbers=numbers, newlines=newlines, spaces=spaces)
        every = [coverage_text(8, newlines, spaces), "0123456789" if numbers == "digits" else "", *texts]
        expected = {piece for text in every for piece in pieces(text, numbers, newlines, spaces)}
        assert set(tokenizer.get_vocab()) == set(SPECIAL_TOKENS) | expected
        # Python's regex (plain texts) and the tokenizer's own agree on every text.
        assert word_level_encoder(tokenizer)(texts) == [tokenizer.encode(t, add_special_tokens=False) for t in texts]


def test_every_text_round_trips_without_unknown_tokens():
    for text in TEXTS:
        ids = TOKENIZER.encode(text, add_special_tokens=False)
        assert TOKENIZER.unk_token_id not in ids
        assert TOKENIZER.decode(ids) == text


def test_every_cell_of_the_frame_is_known_even_if_no_training_text_has_it():
    tokenizer = build_word_tokenizer(["(0, 0)"], frame=20)
    for cell in ("(20, -1)", "(-1, 20)", "(19, 7)"):
        assert tokenizer.convert_tokens_to_ids(cell) != tokenizer.unk_token_id


def test_the_vocabulary_is_deterministic():
    assert build_word_tokenizer(reversed(TEXTS), frame=8).get_vocab() == TOKENIZER.get_vocab()


@settings(max_examples=200, deadline=None)
@given(st.text(alphabet="()-, 0123456789abcupdownleftright\n:.'", max_size=80))
def test_any_text_over_known_pieces_decodes_to_itself_or_marks_unknowns(text):
    ids = TOKENIZER.encode(text, add_special_tokens=False)
    if TOKENIZER.unk_token_id not in ids:
        assert TOKENIZER.decode(ids) == text


def test_labels_cover_gpt_turns_only():
    turns = conversation(WORLDS[0], "bwd", "no-all", "optimal", prompt="paper")
    ids, labels = encode_conversation(TOKENIZER, WORD_LEVEL_FORMAT, turns)
    targets = [t for t, l in zip(ids, labels) if l != -100]
    answer = TOKENIZER.encode(turns[-1]["value"] + "</s>", add_special_tokens=False)
    assert targets == TOKENIZER.encode("OK</s>", add_special_tokens=False) + answer


def test_a_conversation_encodes_as_its_whole_rendered_text():
    # Markers are whole tokens and pieces never span one, so encoding the context runs whole (as a subword
    # tokenizer needs) gives the word-level ids that encoding each piece apart gave before.
    for world in WORLDS[:5]:
        for mode in ("optimal", "reachable"):
            turns = conversation(world, "bwd", "marking-deadend", mode, prompt="paper")
            ids, _ = encode_conversation(TOKENIZER, WORD_LEVEL_FORMAT, turns)
            assert ids == TOKENIZER.encode(render_conversation(WORD_LEVEL_FORMAT, turns), add_special_tokens=False)


@settings(max_examples=300, deadline=None)
@given(st.text(alphabet="()-, 0123456789abcupdownleftright\n:.'<>/shumangpt\té", max_size=80))
def test_the_python_encoder_gives_the_tokenizers_ids_for_any_text(text):
    # Markers anywhere (whole or cut), unknown words, a tab, a non-ASCII letter (the tokenizer's own path).
    encode = word_level_encoder(TOKENIZER)
    for sample in (text, f"<s>{text}</s>", f"<human>{text}<gpt> {text}"):
        assert encode([sample]) == [TOKENIZER.encode(sample, add_special_tokens=False)]


def test_the_python_encoder_serves_saved_copies_and_conversations_alike(tmp_path):
    from transformers import AutoTokenizer

    TOKENIZER.save_pretrained(tmp_path)
    loaded = AutoTokenizer.from_pretrained(tmp_path)
    turns = [conversation(world, "bwd", "marking-deadend", "optimal") for world in WORLDS]
    for tokenizer in (TOKENIZER, loaded):
        encode = word_level_encoder(tokenizer)
        assert encode is not None
        assert encode(["", "up\n(1, 2)"]) == [[], tokenizer.encode("up\n(1, 2)", add_special_tokens=False)]
        assert encode_conversations(tokenizer, WORD_LEVEL_FORMAT, turns, encode) == \
            encode_conversations(tokenizer, WORD_LEVEL_FORMAT, turns)


def test_no_python_encoder_for_other_tokenizers(llama3_tokenizer):
    assert word_level_encoder(llama3_tokenizer) is None  # a subword (BPE) tokenizer
    split = build_word_tokenizer(TEXTS, frame=8)
    split.split_special_tokens = True  # markers read as text: not what the Python encoder does
    assert word_level_encoder(split) is None
