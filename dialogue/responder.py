"""What the agent says back: a rule-based small-talk responder, or an OpenAI-compatible chat endpoint.

`Responder.start(user_text)` returns a `Reply` at once; the caller polls it each step for complete
sentences, so a slow endpoint never blocks a step. The HTTP client streams in a background thread,
and speaks `fallback_text` when the endpoint fails or times out before saying anything.
"""

import datetime
import json
import os
import queue
import re
import threading
import urllib.error
import urllib.request
from typing import Protocol

import numpy as np

_SENTENCE_END = re.compile(r"(?<=[.!?])\s+")


class Reply:
    """Sentences as they become available; `done` once the reply is complete."""

    def __init__(self):
        self._queue: queue.Queue = queue.Queue()
        self.done = False
        self.cancelled = False
        self.error: str | None = None

    def put(self, sentence: str) -> None:
        self._queue.put(sentence)

    def close(self, error: str | None = None) -> None:
        self.error = error
        self._queue.put(None)

    def poll(self) -> list[str]:
        """New complete sentences since the last poll (never blocks)."""
        out = []
        while True:
            try:
                item = self._queue.get_nowait()
            except queue.Empty:
                return out
            if item is None:
                self.done = True
                return out
            out.append(item)

    def cancel(self) -> None:
        self.cancelled = True


class Responder(Protocol):
    def start(self, user_text: str) -> Reply: ...


def split_sentences(text: str) -> list[str]:
    return [s.strip() for s in _SENTENCE_END.split(text) if s.strip()]


# ----------------------------------------------------------------------------------------------- rules

_STOPWORDS = set(
    [
        "a",
        "an",
        "the",
        "and",
        "or",
        "but",
        "if",
        "then",
        "so",
        "of",
        "to",
        "in",
        "on",
        "at",
        "by",
        "for",
        "with",
        "from",
        "up",
        "down",
        "out",
        "over",
        "under",
        "again",
        "i",
        "me",
        "my",
        "mine",
        "myself",
        "we",
        "our",
        "ours",
        "you",
        "your",
        "yours",
        "he",
        "him",
        "his",
        "she",
        "her",
        "hers",
        "it",
        "its",
        "they",
        "them",
        "their",
        "what",
        "which",
        "who",
        "whom",
        "this",
        "that",
        "these",
        "those",
        "am",
        "is",
        "are",
        "was",
        "were",
        "be",
        "been",
        "being",
        "have",
        "has",
        "had",
        "having",
        "do",
        "does",
        "did",
        "doing",
        "would",
        "should",
        "could",
        "can",
        "will",
        "just",
        "not",
        "no",
        "nor",
        "only",
        "own",
        "same",
        "too",
        "very",
        "s",
        "t",
        "don",
        "now",
        "there",
        "here",
        "when",
        "where",
        "why",
        "how",
        "all",
        "any",
        "both",
        "each",
        "few",
        "more",
        "most",
        "other",
        "some",
        "such",
        "than",
        "into",
        "through",
        "during",
        "before",
        "after",
        "above",
        "below",
        "between",
        "off",
        "once",
        "mr",
        "mrs",
        "miss",
        "yes",
        "yeah",
        "okay",
        "ok",
        "oh",
        "um",
        "uh",
        "hmm",
        "well",
        "really",
        "also",
        "about",
        "like",
        "get",
        "got",
        "go",
        "going",
        "know",
        "think",
        "say",
        "said",
        "one",
        "two",
        "consider",
        "want",
        "need",
        "make",
        "take",
        "see",
        "look",
        "come",
        "tell",
        "give",
        "find",
        "feel",
        "try",
        "leave",
        "call",
        "might",
        "must",
        "may",
        "let",
        "put",
        "keep",
        "seem",
    ]
)

_GREETINGS = {"hello", "hi", "hey", "morning", "evening", "afternoon", "greetings"}
_FAREWELLS = {"bye", "goodbye", "farewell", "later", "goodnight"}
_THANKS = {"thanks", "thank", "cheers", "appreciate"}
_QUESTION_WORDS = {
    "what",
    "why",
    "how",
    "where",
    "when",
    "who",
    "which",
    "can",
    "could",
    "do",
    "does",
    "did",
    "is",
    "are",
    "will",
    "would",
    "should",
}
_TOPICS = {
    "weather": {"weather", "rain", "sunny", "sun", "cold", "hot", "snow", "warm", "wind", "raining"},
    "food": {"food", "eat", "eating", "dinner", "lunch", "breakfast", "cook", "cooking", "hungry", "pizza", "coffee"},
    "music": {"music", "song", "songs", "sing", "band", "guitar", "piano", "listen", "concert"},
    "work": {"work", "job", "office", "boss", "project", "meeting", "working", "career"},
    "family": {
        "family",
        "mother",
        "father",
        "brother",
        "sister",
        "son",
        "daughter",
        "children",
        "kids",
        "wife",
        "husband",
        "parents",
    },
    "travel": {"travel", "trip", "holiday", "vacation", "fly", "flight", "city", "country", "visit", "journey"},
    "books": {"book", "books", "read", "reading", "novel", "story", "chapter", "author"},
    "sport": {"sport", "football", "soccer", "tennis", "run", "running", "game", "match", "team", "play"},
    "money": {"money", "pay", "paid", "price", "cost", "income", "fortune", "rich", "poor", "pounds", "dollars"},
}
_RESPONSES = {
    "greeting": [
        "Hello! It's nice to hear from you. How is your day going?",
        "Hi there! What's on your mind today?",
        "Hey! Good to see you. What shall we talk about?",
    ],
    "farewell": [
        "Goodbye! It was lovely talking with you.",
        "Take care, and talk to you soon.",
        "Bye for now. Have a great rest of your day.",
    ],
    "thanks": ["You're very welcome.", "Any time, happy to help.", "My pleasure. Anything else?"],
    "how_are_you": [
        "I'm doing well, thank you for asking. How about you?",
        "Pretty good! I've been enjoying our chat. And you?",
        "I'm great, thanks. What have you been up to?",
    ],
    "name": [
        "I'm a small conversational agent running right here on your computer.",
        "You can call me Miburi. I listen, talk and move while we chat.",
    ],
    "time": ["It's {time} right now.", "My clock says {time}."],
    "weather": [
        "I can't look outside, but I hope the weather is kind to you. Is it nice where you are?",
        "Weather can change a whole day's mood. Do you prefer sunny days or rainy ones?",
    ],
    "food": [
        "Food is one of life's great pleasures. What's your favourite thing to eat?",
        "That sounds tasty. Do you like cooking yourself?",
    ],
    "music": [
        "Music is wonderful. What kind do you listen to most?",
        "I love hearing about music. Is there a song you can't stop playing lately?",
    ],
    "work": [
        "Work can take a lot of energy. How are things going with it?",
        "That sounds busy. What do you enjoy most about your work?",
    ],
    "family": [
        "Family matters a lot. Tell me more about them.",
        "That's sweet. Do you get to spend much time together?",
    ],
    "travel": [
        "Travelling is exciting. Where would you most like to go next?",
        "New places are great. What was the best trip you've taken?",
    ],
    "books": [
        "Stories are a great escape. What are you reading at the moment?",
        "I like a good book too. Who is your favourite author?",
    ],
    "sport": ["Do you play yourself, or mostly watch?", "Sport is a great way to unwind. Which team do you follow?"],
    "money": [
        "Money questions are rarely simple. What would you do with a small fortune?",
        "That's a practical concern. Have you found a plan that works for you?",
    ],
    "question": [
        "That's a good question about {topic}. I'm not sure, but what do you think?",
        "Hmm, {topic}. I'd love to hear your own view on that first.",
        "I don't have a definite answer about {topic}. What made you wonder?",
    ],
    "keyword": [
        "You mentioned {topic}. Tell me more about that.",
        "{Topic}, interesting. What happened next?",
        "I see, {topic}. How do you feel about it?",
        "That sounds important. Why does {topic} matter to you?",
    ],
    "yes": ["Great. Tell me more.", "Good to hear. What else?"],
    "no": ["Okay, fair enough. What would you rather talk about?", "No problem. Is there something else on your mind?"],
    "long": [
        "That was quite a story. The part about {topic} stood out to me. What happened after that?",
        "Thanks for telling me all that. I'm curious about {topic}. Could you say more?",
    ],
    "unclear": [
        "Sorry, I didn't quite catch that. Could you say it again?",
        "I missed that, I'm afraid. One more time?",
    ],
}


class RuleResponder:
    """Keyword, question, greeting and topic rules with several phrasings each; never the same line twice in a row."""

    def __init__(self, seed: int = 0):
        self._rng = np.random.default_rng(seed)
        self._last: dict[str, int] = {}

    def start(self, user_text: str) -> Reply:
        reply = Reply()
        for sentence in split_sentences(self.respond(user_text)):
            reply.put(sentence)
        reply.close()
        return reply

    def respond(self, user_text: str) -> str:
        words = [w for w in re.findall(r"[a-z']+", user_text.lower())]
        wordset = set(words)
        topic_word = _topic_word(words)
        if not words:
            return self._pick("unclear")
        if wordset & _GREETINGS and len(words) <= 6:
            return self._pick("greeting")
        if wordset & _FAREWELLS:
            return self._pick("farewell")
        if wordset & _THANKS:
            return self._pick("thanks")
        if {"how", "you"} <= wordset and ({"are", "doing"} & wordset):
            return self._pick("how_are_you")
        if {"your", "name"} <= wordset or {"who", "you"} <= wordset:
            return self._pick("name")
        if "time" in wordset and ({"what", "the"} & wordset):
            return self._pick("time", time=datetime.datetime.now().strftime("%H:%M"))
        for topic, keys in _TOPICS.items():
            if wordset & keys:
                return self._pick(topic)
        if len(words) <= 2 and wordset & {"yes", "yeah", "sure", "yep"}:
            return self._pick("yes")
        if len(words) <= 2 and wordset & {"no", "nope", "nah"}:
            return self._pick("no")
        if topic_word is None:
            return self._pick("unclear")
        if len(words) > 40:
            return self._pick("long", topic=topic_word)
        if words[0] in _QUESTION_WORDS:
            return self._pick("question", topic=topic_word)
        return self._pick("keyword", topic=topic_word)

    def _pick(self, kind: str, **fields) -> str:
        options = _RESPONSES[kind]
        choices = [i for i in range(len(options)) if i != self._last.get(kind)] or [0]
        i = int(self._rng.choice(choices))
        self._last[kind] = i
        topic = fields.get("topic", "")
        return options[i].format(Topic=topic.capitalize(), **fields)


def _topic_word(words: list[str]) -> str | None:
    """The most telling content word: the longest non-stopword, preferring later ones on ties."""
    content = [w for w in words if w not in _STOPWORDS and len(w) > 2]
    return max(reversed(content), key=len) if content else None


# ------------------------------------------------------------------------------------------- endpoint


class OpenAIChatResponder:
    """Streams /v1/chat/completions (server-sent events) in a thread; keeps a short conversation history."""

    HISTORY_TURNS = 6

    def __init__(
        self,
        url: str,
        model: str,
        timeout_s: float,
        max_tokens: int,
        system_prompt: str,
        fallback_text: str,
        api_key: str | None = None,
    ):
        self.url, self.model, self.timeout_s, self.max_tokens = url, model, timeout_s, max_tokens
        self.system_prompt, self.fallback_text, self.api_key = system_prompt, fallback_text, api_key
        self._history: list[dict] = []

    def start(self, user_text: str) -> Reply:
        reply = Reply()
        messages = [
            {"role": "system", "content": self.system_prompt},
            *self._history,
            {"role": "user", "content": user_text or "(unintelligible)"},
        ]
        threading.Thread(target=self._run, args=(messages, reply), daemon=True, name="chat-endpoint").start()
        return reply

    def _run(self, messages: list[dict], reply: Reply) -> None:
        said: list[str] = []
        try:
            for sentence in self._stream_sentences(messages, reply):
                said.append(sentence)
                reply.put(sentence)
        except (OSError, urllib.error.URLError, ValueError, TimeoutError) as exc:
            if not said:
                reply.put(self.fallback_text)
            reply.close(error=f"{type(exc).__name__}: {exc}")
            return
        if not said:
            reply.put(self.fallback_text)
        self._history = (self._history + [messages[-1], {"role": "assistant", "content": " ".join(said)}])[
            -2 * self.HISTORY_TURNS :
        ]
        reply.close()

    def _stream_sentences(self, messages: list[dict], reply: Reply):
        body = json.dumps(
            {"model": self.model, "messages": messages, "stream": True, "max_tokens": self.max_tokens}
        ).encode()
        headers = {"Content-Type": "application/json", "Accept": "text/event-stream"}
        if self.api_key:
            headers["Authorization"] = f"Bearer {self.api_key}"
        request = urllib.request.Request(self.url, data=body, headers=headers, method="POST")
        text = ""
        with urllib.request.urlopen(request, timeout=self.timeout_s) as response:
            for raw in response:
                if reply.cancelled:
                    return
                line = raw.decode("utf-8", "replace").strip()
                if not line.startswith("data:"):
                    continue
                data = line[5:].strip()
                if data == "[DONE]":
                    break
                text += _delta_text(json.loads(data))
                *complete, text = _split_keep_tail(text)
                yield from complete
        if text.strip():
            yield text.strip()


def _delta_text(event: dict) -> str:
    choices = event.get("choices") or [{}]
    delta = choices[0].get("delta") or choices[0].get("message") or {}
    return delta.get("content") or ""


def _split_keep_tail(text: str) -> list[str]:
    """Complete sentences and the unfinished tail (last element)."""
    parts = _SENTENCE_END.split(text)
    return [p.strip() for p in parts[:-1] if p.strip()] + [parts[-1]]


def build_responder(kind: str, seed: int, **endpoint) -> Responder:
    if kind == "rules":
        return RuleResponder(seed)
    key_env = endpoint.pop("api_key_env")
    return OpenAIChatResponder(api_key=os.environ.get(key_env), **endpoint)
