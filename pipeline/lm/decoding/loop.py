"""The backend-independent part of greedy decoding: result types, and the episode loop of the reachable
setting (env, parsing, transcripts), which drives any backend that can *continue sequences* (`SequenceBackend`):
the HF backend (`pipeline.lm.decoding.hf`) and vLLM (`pipeline.lm.decoding.vllm`).

In the reachable setting an episode keeps its sequence across turns: the env's next observation is encoded
with `encode_followup` and appended; the history is never re-encoded (`HistorySequences` is the baseline
that resubmits it).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable, Iterable, Literal, NamedTuple, Protocol, Sequence

from pipeline.lm.chat import ChatFormat, TextTokenizer, encode_followup, encode_prompt, stop_ids, turn_end_ids
from pipeline.core.environment import EpisodeTranscript, GridEnv, Outcome
from pipeline.core.scoring import parse_action, parse_action_paper
from pipeline.core.texts import DEFAULT_PROMPT, prompt_turns
from pipeline.core.world import World

StopReason = Literal["turn_end", "max_new_tokens", "context", "error"]
# How `play` keeps the history: "cached" is the real thing; the other two are the baselines that
# benchmarks/bench_decode.py measures it against (and tests compare it with).
HistoryStrategy = Literal["cached", "reencode", "generate"]
# (answer text, observation the answer replies to) -> the move to play, or None (INVALID).
MoveChooser = Callable[[str, str], "str | None"]


@dataclass(frozen=True)
class Generation:
    """One optimal-setting answer. `finished`: it ended with the turn-end ids, which `text` leaves out and
    `n_tokens` (the tokens generated) counts."""

    text: str
    n_tokens: int
    finished: bool
    stop_reason: StopReason
    error: str | None = None


@dataclass
class DecodedEpisode:
    """One reachable-setting episode as the decoder played it: the env's transcript plus the model's raw
    answers and the tokens they took (unscored: `pipeline.core.episodes` scores it).

    `error` is set (and `transcript.outcome` is None) when the prompt or the growing history no longer fits
    the model's context; the episode then stops where it was.
    """

    world_index: int
    transcript: EpisodeTranscript
    answers: list[str]
    n_tokens: int
    error: str | None = None

    @property
    def outcome(self) -> Outcome | None:
        return self.transcript.outcome

    @property
    def moves(self) -> list[str]:
        return self.transcript.moves

    @property
    def n_moves(self) -> int:
        return self.transcript.n_moves


class Request(NamedTuple):
    """Ids to append to a sequence (a new key starts one), and the cap on the tokens generated after them."""

    ids: list[int]
    max_new_tokens: int


@dataclass(frozen=True)
class Continuation:
    """What a backend generated for one sequence: new ids without the turn-end ids, and why it stopped."""

    ids: list[int]
    stop_reason: StopReason
    error: str | None = None

    n_stop: int = 0  # the turn-end ids generated after `ids`

    @property
    def finished(self) -> bool:
        return self.stop_reason == "turn_end"

    @property
    def n_tokens(self) -> int:
        return len(self.ids) + self.n_stop


class SequenceBackend(Protocol):
    """What the episode loop needs of a backend: keyed token sequences it can extend and continue."""

    def continue_sequences(self, requests: dict[int, Request]) -> dict[int, Continuation]:
        """Append each request's ids to its sequence, then greedily generate until the turn ends."""
        ...

    def release(self, keys: Iterable[int]) -> None:
        """Forget these sequences (unknown keys are ignored)."""
        ...


def generation(tokenizer: TextTokenizer, out: Continuation) -> Generation:
    """A continuation as an optimal-setting answer."""
    text = tokenizer.decode(out.ids, skip_special_tokens=False)
    return Generation(text, out.n_tokens, out.finished, out.stop_reason, out.error)


def context_error(n_tokens: int, max_length: int) -> str:
    """The per-item message for a sequence that leaves no room to generate within the context."""
    return f"sequence of {n_tokens} tokens leaves no room to generate within the context of {max_length}"


# ----------------------------------------------------------------------------------------------------
# The shared episode loop


@dataclass
class _Episode:
    index: int
    env: GridEnv
    observation: str
    answers: list[str] = field(default_factory=list)
    n_tokens: int = 0


def play_episodes(
    backend: SequenceBackend,
    tokenizer: TextTokenizer,
    fmt: ChatFormat,
    worlds: Sequence[World],
    *,
    batch_size: int,
    max_moves: int = 200,
    max_new_tokens: int = 4096,
    max_followup_tokens: int = 64,
    on_episode: Callable[[DecodedEpisode], None] | None = None,
    choose_move: MoveChooser | None = None,
    prompt: str = DEFAULT_PROMPT,
    rules: str = "project",
) -> list[DecodedEpisode]:
    """Play one episode per world, up to `batch_size` at a time; a finished episode's slot is refilled.

    Each turn every live episode's sequence is continued once; the answer is parsed into a move
    (`choose_move`, default `scoring.parse_action`), the env steps, and the next observation is appended.
    An answer cut at its cap (`max_new_tokens` for the first answer, `max_followup_tokens` for later ones)
    is scored as it stands and, if the episode goes on, closed with the turn-end ids.
    `on_episode` is called as each episode ends (in order of ending); the list returned is in input order.
    `prompt` is the prompt form (`texts.PROMPTS`) the model was trained with; `rules` how episodes are
    judged (`environment.RULES`: ours, or the paper's harness, which also reads the move its own way).
    """
    parse = parse_action_paper if rules == "paper" else parse_action
    choose = choose_move or (lambda text, _observation: parse(text))
    end_ids = turn_end_ids(tokenizer, fmt)
    after_stop = end_ids[len(stop_ids(tokenizer, fmt)):]  # what closes a turn the decoder stopped
    pending_worlds = iter(enumerate(worlds))
    results: list[DecodedEpisode | None] = [None] * len(worlds)
    live: dict[int, _Episode] = {}
    requests: dict[int, Request] = {}

    def finish(episode: _Episode, error: str | None = None) -> None:
        del live[episode.index]
        requests.pop(episode.index, None)
        result = DecodedEpisode(episode.index, episode.env.transcript(), episode.answers, episode.n_tokens, error)
        results[episode.index] = result
        if on_episode is not None:
            on_episode(result)

    while True:
        while len(live) < batch_size and (item := next(pending_worlds, None)) is not None:
            index, world = item
            env = GridEnv(world, max_moves=max_moves, rules=rules)
            live[index] = _Episode(index, env, env.reset())
            requests[index] = Request(encode_prompt(tokenizer, fmt, prompt_turns(world, prompt)), max_new_tokens)
        if not live:
            break
        continuations = backend.continue_sequences(requests)
        requests = {}
        ended = []
        for key, cont in continuations.items():
            episode = live[key]
            episode.n_tokens += cont.n_tokens
            if cont.error is not None or cont.stop_reason == "context":
                if cont.ids:
                    episode.answers.append(tokenizer.decode(cont.ids, skip_special_tokens=False))
                finish(episode, cont.error or "the history reached the end of the context")
                ended.append(key)
                continue
            text = tokenizer.decode(cont.ids, skip_special_tokens=False)
            episode.answers.append(text)
            step = episode.env.step(choose(text, episode.observation), text)
            if step.done:
                finish(episode)
                ended.append(key)
                continue
            episode.observation = step.observation
            closing = after_stop if cont.finished else end_ids
            requests[key] = Request(closing + encode_followup(tokenizer, fmt, step.observation), max_followup_tokens)
        backend.release(ended)
    return [r for r in results if r is not None]


class HistorySequences:
    """A backend that keeps each sequence's ids and resubmits the whole history every turn.

    `continue_prompts(prompts, caps)` continues whole token sequences; vLLM's prefix cache makes this
    cheap there, while for HF it is the re-encoding baseline.
    """

    def __init__(
        self,
        continue_prompts: Callable[[list[list[int]], list[int]], list[Continuation]],
        stop_ids: list[int],
        max_length: int,
    ):
        self.continue_prompts, self.stop_ids, self.max_length = continue_prompts, stop_ids, max_length
        self.history: dict[int, list[int]] = {}

    def release(self, keys: Iterable[int]) -> None:
        for key in keys:
            self.history.pop(key, None)

    def continue_sequences(self, requests: dict[int, Request]) -> dict[int, Continuation]:
        results: dict[int, Continuation] = {}
        keys = []
        for key, req in requests.items():
            history = self.history[key] = self.history.get(key, []) + list(req.ids)
            if len(history) >= self.max_length:
                results[key] = Continuation([], "error", context_error(len(history), self.max_length))
            else:
                keys.append(key)
        if keys:
            outs = self.continue_prompts([self.history[k] for k in keys], [requests[k].max_new_tokens for k in keys])
            for key, out in zip(keys, outs):
                self.history[key] += out.ids + (self.stop_ids if out.finished else [])
                results[key] = out
        return results
