"""A generator of varied small-talk sentences and backchannels (seeded, no external text).

Sentences come from templates with slots filled from topic vocabularies; questions, statements, opinions
and stories, with optional openers ("well", "you know") and tails, so that turns vary in length and rhythm.
"""

from __future__ import annotations

import numpy as np

_SLOTS = {
    "place": [
        "the lake",
        "the mountains",
        "my sister's place",
        "the city",
        "the coast",
        "the old market",
        "a tiny village",
        "the park downtown",
        "the new museum",
        "the beach",
        "Lisbon",
        "the countryside",
    ],
    "food": [
        "pasta",
        "fresh bread",
        "spicy noodles",
        "a huge breakfast",
        "soup",
        "grilled fish",
        "pancakes",
        "curry",
        "tacos",
        "apple pie",
        "dumplings",
        "a salad",
    ],
    "activity": [
        "hiking",
        "painting",
        "running",
        "gardening",
        "cooking",
        "reading",
        "cycling",
        "swimming",
        "playing the guitar",
        "learning French",
        "baking",
        "photography",
    ],
    "thing": [
        "the weather",
        "the traffic",
        "that new show",
        "the concert",
        "the game last night",
        "my new job",
        "the meeting",
        "the neighbours",
        "the football match",
        "the holidays",
        "the project",
        "the exam",
    ],
    "time": [
        "last weekend",
        "yesterday",
        "this morning",
        "last summer",
        "on Friday",
        "a few days ago",
        "last month",
        "over the holidays",
        "the other night",
        "on Sunday",
    ],
    "person": [
        "my brother",
        "a friend of mine",
        "my neighbour",
        "my colleague",
        "my grandmother",
        "our teacher",
        "my cousin",
        "an old friend",
    ],
    "feeling": [
        "amazing",
        "a bit strange",
        "really relaxing",
        "exhausting",
        "so much fun",
        "surprisingly good",
        "pretty boring",
        "wonderful",
        "quite stressful",
        "lovely",
    ],
    "adj": ["huge", "quiet", "crowded", "beautiful", "tiny", "noisy", "warm", "cold", "bright", "busy"],
}

_TEMPLATES = [
    "I went to {place} {time}, and honestly it was {feeling}.",
    "Have you ever been to {place}?",
    "{person} told me about {thing}, and I could not stop laughing.",
    "What do you usually do on the weekend?",
    "I have been getting into {activity} lately.",
    "Do you like {activity}?",
    "We had {food} {time}, it was {feeling}.",
    "The best thing about {place} is that it is so {adj}.",
    "I think {thing} was {feeling}, to be honest.",
    "How was {thing}?",
    "I really should try {activity} one day.",
    "Did you hear about {thing}?",
    "{time} I met {person} at {place}.",
    "It was {adj}, and there were people everywhere.",
    "I am not sure, but I think it starts at seven.",
    "That sounds {feeling}!",
    "Oh, I love {food}, especially when it is {adj}.",
    "We should go to {place} together sometime.",
    "What kind of {food} do you like?",
    "I spent the whole afternoon {activity}, and it was {feeling}.",
    "Honestly, {thing} is the only thing people talk about.",
    "Why do you think {thing} was so {feeling}?",
    "My favourite place is {place}, because it is so {adj}.",
    "{person} is really into {activity} now.",
    "Let me tell you what happened {time}.",
    "There was this {adj} dog that followed us all the way to {place}.",
    "I would rather stay home and cook {food}.",
    "Wait, are you serious?",
    "So what happened next?",
    "That reminds me of {thing}.",
    "I have never tried {activity}, is it hard?",
    "You know, {place} is much more {adj} than I expected.",
]

_OPENERS = ["Well,", "So,", "You know,", "Actually,", "Oh,", "Yeah,", "Right,", "Hmm,", "Anyway,", "I mean,"]
_TAILS = [" right?", " you know?", " I think.", " really.", " anyway."]

BACKCHANNELS = ("mm-hmm", "yeah", "right", "uh-huh", "okay", "I see", "oh really", "wow", "sure", "mm")


class SentenceGenerator:
    """Draws sentences and backchannels from a numpy Generator (deterministic for a given seed)."""

    def __init__(self, rng: np.random.Generator):
        self.rng = rng

    def _pick(self, items):
        return items[int(self.rng.integers(len(items)))]

    def sentence(self) -> str:
        text = self._pick(_TEMPLATES)
        for slot, words in _SLOTS.items():
            while "{" + slot + "}" in text:
                text = text.replace("{" + slot + "}", self._pick(words), 1)
        text = text[0].upper() + text[1:]
        if self.rng.random() < 0.25:
            first = text.split(" ", 1)[0]
            text = f"{self._pick(_OPENERS)} {text if first in ('I', 'I am') else text[0].lower() + text[1:]}"
        if self.rng.random() < 0.1 and text.endswith("."):
            text = text[:-1] + "," + self._pick(_TAILS)
        return text

    def backchannel(self) -> str:
        return self._pick(BACKCHANNELS)
