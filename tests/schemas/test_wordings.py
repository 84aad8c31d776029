"""The held-out wordings: words the task generator never says, the same wording every time, and a
training lexicon that shares none of them."""

import re

from pathlib import Path

import schemas
from schemas.config import TasksConfig
from schemas.wordings import (HELD_OUT_COLOURS, HELD_OUT_NOUNS, HELD_OUT_PHRASES, TRAINING_LEXICON, held_out_wording,
                              training_variants)
from envs.suite import generate_tasks, suite_tasks
from stages.evaluate import evaluation_cases


SPEC_TEXT = " ".join(p.read_text() for p in (Path(schemas.__file__).parent / "task_specs").glob("*.yaml"))


def _words(text: str) -> set[str]:
    return set(re.findall(r"[a-z]+", text.lower()))


def test_no_task_of_the_suite_is_ever_said_with_a_held_out_word():
    tasks = suite_tasks()
    assert len(tasks) > 100
    generated = _words(SPEC_TEXT)  # every word of the spec files: templates, held-back templates, and more
    held_out = set().union(*(_words(new) for new in [*HELD_OUT_COLOURS.values(), *(n for _, n in HELD_OUT_PHRASES),
                                                      *(n for _, n in HELD_OUT_NOUNS)]))
    held_out -= {"up", "to", "down"}  # particles the templates use too
    assert not generated & held_out, sorted(generated & held_out)
    for task in tasks:
        wording = held_out_wording(task.instruction)
        assert wording not in task.instructions + task.unseen_instructions
        assert held_out_wording(task.instruction) == wording  # fixed: every model meets the same words
        for colour in task.object_colours.values():  # a colour is never said with its own word
            assert not re.search(rf"\b{colour}\b", wording), wording


def test_a_coloured_instruction_is_reworded_in_colour_verb_noun_and_shape():
    wording = held_out_wording("pick up the red block")
    assert "crimson" in wording and "snatch up" in wording and "brick" in wording and wording != "snatch up the crimson brick"


def test_the_training_lexicon_shares_no_word_with_the_held_out_one():
    training = set().union(*(_words(w) for w in [*TRAINING_LEXICON["colours"].values(),
                                                 *(n for _, n in TRAINING_LEXICON["phrases"]),
                                                 *(n for _, n in TRAINING_LEXICON["nouns"]), *TRAINING_LEXICON["shapes"]]))
    held = set().union(*(_words(w) for w in [*HELD_OUT_COLOURS.values(), *(n for _, n in HELD_OUT_PHRASES),
                                             *(n for _, n in HELD_OUT_NOUNS)]))
    assert not training & held - {"up", "to", "you"}, training & held
    variants = training_variants("pick up the red block", 4)
    assert len(variants) == 4 and all("scarlet" in v for v in variants)


def test_the_split_is_evaluated_only_when_asked_and_only_for_seen_tasks():
    tasks = generate_tasks(TasksConfig(specs=["lift"], colours=["red", "green", "blue", "yellow"],
                                       unseen_colours=["yellow"]), 0)
    assert not [c for c in evaluation_cases(tasks) if c[1] == "held_out_wording"]
    reworded = [c for c in evaluation_cases(tasks, True) if c[1] == "held_out_wording"]
    assert sorted(t.task_id for t, _, _ in reworded) == ["lift-blue", "lift-green", "lift-red"]
