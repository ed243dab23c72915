"""data-build: deterministic, byte-identical files; splits shared by all variants; disjoint train/test."""

import json

import pytest

from pipeline.core.checks import SettingError
from pipeline.lm.chat import UNTRAINED, read_conversations
from pipeline.lm.model_settings import ModelSettings
from pipeline.workflow.data_build import (
    DataSettings,
    TEST_CONVERSATIONS, TEST_WORLDS, TRAIN_CONVERSATIONS, TextSettings, build_splits, dataset_sha256,
    untrained_words, untrained_words_line, validation_worlds, write_dataset,
)
from pipeline.core.world import World, load_worlds


def _data(**overrides):
    values = dict(train_size_x=[2, 4], train_size_y=[2, 4], test_size_x=[2, 5], test_size_y=[2, 5], frame=6,
                  p_pit=[0.1, 0.5], n_train=40, n_test=10, test_file=None, seed=3, workers=1)
    values.update(overrides)
    return DataSettings(**values)


def test_same_config_gives_byte_identical_files(tmp_path):
    spec = TextSettings.of("bwd", "marking-deadend", "optimal")
    hashes = []
    for name in ("a", "b"):
        train, test = build_splits(_data(workers=1 if name == "a" else 2))
        write_dataset(tmp_path / name, train, test, spec, (4, 4))
        hashes.append(dataset_sha256(tmp_path / name))
    assert hashes[0] == hashes[1]
    other = build_splits(_data(seed=4))
    assert [w.key() for w in other[1]] != [w.key() for w in build_splits(_data())[1]]


def test_train_and_test_are_disjoint_and_sized():
    train, test = build_splits(_data())
    assert len(train) == 40 and len(test) == 10
    assert not {w.key() for w in train} & {w.key() for w in test}
    assert all(w.size_x <= 4 and w.size_y <= 4 for w in train)


def test_every_variant_sees_the_same_worlds(tmp_path):
    train, test = build_splits(_data())
    for variant in ("marking-deadend", "no-all", "none", "cot"):
        out = tmp_path / variant
        write_dataset(out, train, test, TextSettings.of("fwd", variant, "optimal"), (4, 4))
        assert [w.key() for w in load_worlds(out / TEST_WORLDS)] == [w.key() for w in test]
        conversations = read_conversations(out / TRAIN_CONVERSATIONS)
        assert len(conversations) == 40 and conversations[0][0]["from"] == "human"
        golden = read_conversations(out / TEST_CONVERSATIONS)
        assert golden[0][-1]["value"].startswith("Thought:" if variant != "none" else "Plan:")


def test_the_task_prompt_drops_the_instruction_turns_and_nothing_else(tmp_path):
    train, test = build_splits(_data())
    for prompt in ("paper", "task"):
        write_dataset(tmp_path / prompt, train, test, TextSettings.of("bwd", "marking-deadend", "optimal", prompt=prompt),
                      (4, 4))
    paper, task = (read_conversations(tmp_path / p / TRAIN_CONVERSATIONS) for p in ("paper", "task"))
    assert [turns[2:] for turns in paper] == task
    assert all(len(turns) == 2 and turns[0]["value"].startswith("Grid is from") for turns in task)
    assert TextSettings.of("bwd", "marking-deadend", "optimal", prompt="task") != TextSettings.of(
        "bwd", "marking-deadend", "optimal", prompt="paper")
    assert TextSettings.of("bwd", "marking-deadend", "optimal").prompt == ModelSettings().prompt  # one default


def test_direction_free_baselines_share_one_text_spec():
    assert TextSettings.of("fwd", "none", "optimal") == TextSettings.of("bwd", "none", "optimal")
    assert TextSettings.of("fwd", "dfs", "reachable") == TextSettings.of("bwd", "dfs", "reachable")
    assert TextSettings.of("fwd", "cot", "optimal") != TextSettings.of("bwd", "cot", "optimal")


def test_an_anchored_plan_is_a_text_setting_only_where_the_answer_has_a_plan_and_a_thought():
    anchored = TextSettings.of("bwd", "marking-deadend", "optimal", plan_form="anchored")
    assert anchored.plan_form == "anchored" and anchored != TextSettings.of("bwd", "marking-deadend", "optimal")
    assert TextSettings.of("bwd", "cot", "optimal", plan_form="anchored").plan_form == "anchored"
    assert TextSettings.of("fwd", "none", "optimal", plan_form="anchored") == TextSettings.of("fwd", "none", "optimal")
    assert TextSettings.of("bwd", "marking-deadend", "reachable", plan_form="anchored") == TextSettings.of(
        "bwd", "marking-deadend", "reachable")
    with pytest.raises(SettingError, match="plan_form='cells'.*one of moves, anchored"):
        ModelSettings(plan_form="cells")


def test_the_papers_test_file_can_be_the_test_split(paper_test_file):
    train, test = build_splits(_data(test_file=str(paper_test_file), n_test=25, n_train=5))
    with open(paper_test_file) as handle:
        first = [World.from_json(json.loads(next(handle))) for _ in range(25)]
    assert test == first


def test_asking_for_more_test_worlds_than_the_file_holds_names_the_limit(paper_test_file):
    with pytest.raises(ValueError, match="n_test=5000.*3000"):
        build_splits(_data(test_file=str(paper_test_file), n_test=5000))


def test_untrained_words_names_the_step_numbers_only_larger_test_worlds_need(tmp_path, capsys):
    """Numbered headers: test maps longer than any training map need step numbers training never wrote; the
    summary counts them per word and the worlds needing one; plain headers need none."""
    data = _data(train_size_x=[2, 2], train_size_y=[2, 2], test_size_x=[5, 6], test_size_y=[5, 6], n_train=30)
    train, test = build_splits(data)
    longest_train = max(len(w.optimal_moves()) for w in train)
    numbered = write_dataset(tmp_path / "numbered", train, test, TextSettings.of("bwd", "no-all", "optimal"), (2, 2))
    found = numbered["untrained_words"]
    expected = {f" {k}" for w in test for k in range(longest_train + 1, len(w.optimal_moves()) + 1)}
    assert expected and expected <= set(found["words"])
    assert found["words"][f" {longest_train + 1}"] == sum(len(w.optimal_moves()) > longest_train for w in test)
    assert 0 < found["n_worlds"] <= found["n_test"] == len(test) and found["n_words"] == len(found["words"])
    line = untrained_words_line(found)
    assert line.startswith(f"[data-build] {found['n_worlds']} of {len(test)} test worlds need words") and "' " in line
    plain = write_dataset(tmp_path / "plain", train, test,
                          TextSettings.of("bwd", "no-all", "optimal", step_headers="plain"), (2, 2))
    assert not any(word.strip().isdigit() for word in plain["untrained_words"]["words"])
    # Digits (model.numbers=digits): a step number is its digits, so only digits no training map reached are
    # untrained, and every header's space is a token of its own.
    digits = write_dataset(tmp_path / "digits", train, test,
                           TextSettings.of("bwd", "no-all", "optimal", numbers="digits"), (2, 2))
    numbers = {word for word in digits["untrained_words"]["words"] if word.strip().isdigit()}
    assert numbers == {digit for word in expected for digit in word.strip()} - set(
        "".join(str(k) for k in range(1, longest_train + 1)))
    assert digits["train_tokens"]["mean"] > numbered["train_tokens"]["mean"]


def test_untrained_words_counts_each_world_once():
    found = untrained_words({"a", "b"}, [frozenset({"a", "c", "d"}), frozenset({"b"}), frozenset({"c"})])
    assert found == {"words": {"c": 2, "d": 1}, "n_words": 2, "n_worlds": 2, "n_test": 3}
    assert untrained_words_line(untrained_words({"a"}, [frozenset({"a"})])) is None


def test_validation_worlds_follow_the_test_sizes_and_are_disjoint_from_both_splits():
    data = _data(n_train=200, n_test=20)
    train, test = build_splits(data)
    valid = validation_worlds(data, 30, train, test)
    assert len(valid) == 30 and valid == validation_worlds(_data(n_train=200, n_test=20, workers=2), 30, train, test)
    keys = {w.key() for w in valid}
    assert len(keys) == 30 and not keys & {w.key() for w in (*train, *test)}
    assert all(2 <= w.size_x <= 5 and 2 <= w.size_y <= 5 for w in valid)
    assert any(w.size_x > 4 or w.size_y > 4 for w in valid)  # the test distribution, not the training one


def test_distractors_change_the_train_prompts_only(tmp_path):
    """`train_distractors` (not in the paper): the same worlds; train prompts list extra obstacles outside the
    grid, train answers and every test text are as they were; a data setting at its default changes nothing."""
    data = _data(train_distractors=8)
    assert build_splits(data) == build_splits(_data())
    train, test = build_splits(data)
    spec = TextSettings.of("bwd", "marking-deadend", "optimal")
    write_dataset(tmp_path / "plain", train, test, spec, (4, 4))
    write_dataset(tmp_path / "again", train, test, spec, (4, 4), 0, 6)
    write_dataset(tmp_path / "extra", train, test, spec, (4, 4), 8, 6)
    assert dataset_sha256(tmp_path / "plain") == dataset_sha256(tmp_path / "again")
    assert (tmp_path / "plain" / TEST_CONVERSATIONS).read_bytes() == (tmp_path / "extra" / TEST_CONVERSATIONS).read_bytes()
    plain, extra = (read_conversations(tmp_path / name / TRAIN_CONVERSATIONS) for name in ("plain", "extra"))
    assert [c[1:] for c in plain] == [c[1:] for c in extra]
    longer = [len(b[0]["value"]) - len(a[0]["value"]) for a, b in zip(plain, extra)]
    assert min(longer) >= 0 and sum(n > 0 for n in longer) > len(longer) // 2
    with pytest.raises(ValueError, match="train_distractors=-1 is not allowed; expected an integer >= 0"):
        _data(train_distractors=-1)


def test_masked_edge_labels_list_cut_labels_of_train_answers_and_change_no_text(tmp_path):
    """`mask_edge_labels` (not in the paper): the same worlds and texts; each train answer lists its edge labels
    (`texts.edge_label_spans`) as untrained spans, each a `cut` after a cell outside the grid; test texts are
    byte for byte as they were; the summary counts them."""
    data = _data(mask_edge_labels=True)
    assert build_splits(data) == build_splits(_data())
    train, test = build_splits(data)
    spec = TextSettings.of("bwd", "marking-deadend", "optimal")
    plain = write_dataset(tmp_path / "plain", train, test, spec, (4, 4))
    masked = write_dataset(tmp_path / "masked", train, test, spec, (4, 4), mask_edge=True)
    assert (tmp_path / "plain" / TEST_CONVERSATIONS).read_bytes() == (tmp_path / "masked" / TEST_CONVERSATIONS).read_bytes()
    before, after = (read_conversations(tmp_path / name / TRAIN_CONVERSATIONS) for name in ("plain", "masked"))
    assert [[t["value"] for t in c] for c in before] == [[t["value"] for t in c] for c in after]
    answers = [c[1] for c in after]
    spans = [(a["value"], span) for a in answers for span in a[UNTRAINED]]
    assert plain["untrained_edge_labels"] == 0 and masked["untrained_edge_labels"] == len(spans) > 0
    assert {value[a:b] for value, (a, b) in spans} == {"cut"}
    assert all(value[a - 1] == "\n" and value[b:b + 1] in ("", "\n") for value, (a, b) in spans)
    assert sum(bool(a[UNTRAINED]) for a in answers) > len(answers) // 4


def test_deep_train_worlds_leave_the_test_and_validation_splits_as_they_were():
    """`train_deep` (not in the paper) draws deep train worlds only: the test split is the same, validation
    worlds are still corner to corner (drawn disjoint from another train split, so not the same ones)."""
    plain, deep = build_splits(_data()), build_splits(_data(train_deep=1.0))
    assert deep[1] == plain[1]
    assert all(w.start == (w.x0, w.y0) and w.goal == (w.x1, w.y1) for w in plain[0])
    assert sum(w.start != (w.x0, w.y0) or w.goal != (w.x1, w.y1) for w in deep[0]) > 20
    data = _data(train_deep=1.0)
    assert data.generator_config("train").deep == 1.0 and data.generator_config("test").deep == 0.0
    assert all(w.start == (w.x0, w.y0) and w.goal == (w.x1, w.y1) for w in validation_worlds(data, 10, *deep))
