"""Instructions worded as the task generator never words them (issue 9, item 7): the held-out wording
split. A task's canonical instruction is rewritten with words no spec template or colour list uses:
other words for its colours, its verbs and its objects, and another sentence shape (a polite request,
a wish, a question). The policy has only met the templates' words; this split measures whether it
follows the request or keys on the tokens it was trained with.

The rewrite is a fixed function of the instruction (no randomness): every model meets the same
wording, and `sim2act eval` on another day meets it again. Its lexicon is disjoint from the one
training may use to augment instructions (`TRAINING_LEXICON`), so augmentation cannot teach the
held-out words themselves.
"""

from __future__ import annotations

import hashlib
import re

HELD_OUT_WORDING = "held_out_wording"  # the evaluation split

# colour -> a word for it no spec uses
HELD_OUT_COLOURS = {"red": "crimson", "green": "emerald", "blue": "navy", "yellow": "golden", "purple": "violet",
                    "orange": "tangerine"}
# phrase -> phrase, first match wins, whole words; verbs and objects no template says
HELD_OUT_PHRASES = [
    ("pick up", "snatch up"), ("lift", "heave up"), ("grab", "clutch"), ("raise", "elevate"), ("take", "seize"),
    ("stack", "pile"), ("put", "deposit"), ("place", "deposit"), ("set", "lay"), ("move", "shift"),
    ("drop", "release"), ("fit", "mount"), ("slide", "lower"), ("go to", "proceed to"), ("walk to", "wander to"),
    ("drive to", "travel to"), ("find", "track down"), ("open", "pry apart"), ("close", "seal"), ("push", "shove"),
    ("press", "depress"), ("turn", "spin"), ("pull", "tug"),
]
HELD_OUT_NOUNS = [("block", "brick"), ("cube", "brick"), ("room", "chamber"), ("ball", "sphere"), ("box", "parcel"),
                  ("bin", "bucket"), ("peg", "pole"), ("nut", "washer")]
# sentence shapes, `{}` the rewritten request
HELD_OUT_SHAPES = ["could you {} for me, please?", "I would like you to {}.", "please {} now.",
                   "would you kindly {}?", "your job: {}."]

# what training may augment with (train.language_augment): other words, none of the held-out ones
TRAINING_LEXICON = {
    "colours": {"red": "scarlet", "green": "lime", "blue": "cobalt", "yellow": "lemon", "purple": "plum",
                "orange": "apricot"},
    "phrases": [("pick up", "get"), ("lift", "pick up"), ("stack", "put"), ("put", "set"), ("go to", "go into"),
                ("place", "put")],
    "nouns": [("block", "cube"), ("cube", "block")],
    "shapes": ["{}", "{} please", "can you {}", "now {}", "i want you to {}"],
}


def plain(text: str) -> str:
    """`text` as a comparison sees it: lower case, words only (MiniLM is uncased and ignores most
    punctuation, so "Lift the red block." and "lift the red block" are one instruction to it)."""
    return " ".join(re.findall(r"[a-z0-9]+", text.lower()))


# every word or phrase the held-out wording introduces: training text must say none of them
HELD_OUT_VOCABULARY = sorted({new for _, new in [*HELD_OUT_COLOURS.items(), *HELD_OUT_PHRASES, *HELD_OUT_NOUNS]})


def held_out_word_in(text: str) -> str | None:
    """The first held-out word or phrase `text` says (whole words, any case), else None."""
    said = f" {plain(text)} "
    return next((word for word in HELD_OUT_VOCABULARY if f" {word} " in said), None)


def _substitute(text: str, pairs: list[tuple[str, str]], every: bool) -> str:
    """Replace whole-word occurrences of the pairs' first phrase: the first pair found, or every pair."""
    for old, new in pairs:
        pattern = rf"\b{re.escape(old)}\b"
        if re.search(pattern, text):
            text = re.sub(pattern, new, text)
            if not every:
                return text
    return text


def _pick(options: list[str], key: str) -> str:
    return options[int.from_bytes(hashlib.blake2b(key.encode(), digest_size=4).digest(), "little") % len(options)]


def reword(instruction: str, colours: dict[str, str], phrases: list[tuple[str, str]], nouns: list[tuple[str, str]],
           shapes: list[str], key: str) -> str:
    """`instruction` with its colour words, its first verb phrase and its object nouns replaced, in a
    sentence shape chosen by `key`."""
    text = instruction.strip().rstrip(".").lower()
    text = _substitute(text, list(colours.items()), every=True)
    text = _substitute(text, phrases, every=False)
    text = _substitute(text, nouns, every=True)
    return _pick(shapes, key).format(text)


def held_out_wording(instruction: str) -> str:
    """The held-out wording of a canonical instruction."""
    return reword(instruction, HELD_OUT_COLOURS, HELD_OUT_PHRASES, HELD_OUT_NOUNS, HELD_OUT_SHAPES, instruction)


def training_variants(instruction: str, count: int) -> list[str]:
    """Up to `count` distinct rewordings of a training instruction with TRAINING_LEXICON (for augmentation)."""
    lexicon = TRAINING_LEXICON
    variants = []
    for shape in lexicon["shapes"]:
        for phrases in (lexicon["phrases"], []):
            text = reword(instruction, lexicon["colours"], phrases, lexicon["nouns"], [shape], "")
            if text != instruction and text not in variants:
                variants.append(text)
    return variants[:count]
