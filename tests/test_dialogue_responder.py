"""Responders: varied rule-based small talk, and an OpenAI-compatible streaming endpoint (a real local server)."""

import json
import threading
import time
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import numpy as np
import pytest

from dialogue.responder import OpenAIChatResponder, RuleResponder
from tests.dialogue_helpers import LIBRIVOX, dialogue_cfg, load_24k, run_component, silence

FALLBACK = "Sorry, I can't reach my language model right now. Could you say that again in a moment?"


def wait_reply(reply, timeout_s=10.0):
    sentences, t0 = [], time.monotonic()
    while not reply.done and time.monotonic() - t0 < timeout_s:
        sentences += reply.poll()
        time.sleep(0.01)
    return sentences + reply.poll()


def test_rules_react_to_what_was_said():
    r = RuleResponder(seed=0)
    assert "?" in r.respond("hello") or "!" in r.respond("hello")
    assert "food" in r.respond("i really like pizza").lower() or "eat" in r.respond("i like pizza").lower()
    assert ":" in r.respond("what time is it")
    assert "dashwood" in r.respond("mr john dashwood had then leisure").lower()
    assert "catch" in r.respond("").lower() or "missed" in r.respond("").lower()


def test_rules_never_repeat_a_line_back_to_back_and_vary():
    r = RuleResponder(seed=1)
    answers = [r.respond("hello there") for _ in range(12)]
    assert all(a != b for a, b in zip(answers, answers[1:]))
    assert len(set(answers)) >= 3
    topics = {
        r.respond(t)
        for t in (
            "i went on a trip to rome",
            "my sister plays the piano",
            "my boss is strict",
            "it is raining again",
            "why do cats purr",
            "thanks a lot",
            "goodbye",
        )
    }
    assert len(topics) == 7


class _ChatHandler(BaseHTTPRequestHandler):
    """Streams a fixed answer as OpenAI chat-completion chunks (server-sent events), word by word."""

    answer = "Hello from the test server. It streams word by word!"
    requests: list = []

    def do_POST(self):
        body = json.loads(self.rfile.read(int(self.headers["Content-Length"])))
        type(self).requests.append(body)
        self.send_response(200)
        self.send_header("Content-Type", "text/event-stream")
        self.end_headers()
        for word in self.answer.split(" "):
            chunk = {"choices": [{"delta": {"content": word + " "}}]}
            self.wfile.write(f"data: {json.dumps(chunk)}\n\n".encode())
            self.wfile.flush()
            time.sleep(0.01)
        self.wfile.write(b"data: [DONE]\n\n")

    def log_message(self, *args):
        pass


@pytest.fixture()
def chat_server():
    _ChatHandler.requests = []
    server = ThreadingHTTPServer(("127.0.0.1", 0), _ChatHandler)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    yield f"http://127.0.0.1:{server.server_address[1]}/v1/chat/completions"
    server.shutdown()
    server.server_close()


def _endpoint(url, timeout_s=2.0):
    return OpenAIChatResponder(
        url=url, model="test", timeout_s=timeout_s, max_tokens=50, system_prompt="be brief", fallback_text=FALLBACK
    )


def test_endpoint_streams_sentences_and_keeps_history(chat_server):
    responder = _endpoint(chat_server)
    assert wait_reply(responder.start("hi there")) == ["Hello from the test server.", "It streams word by word!"]
    wait_reply(responder.start("and again"))
    second = _ChatHandler.requests[-1]
    assert second["stream"] is True and second["model"] == "test"
    assert [m["role"] for m in second["messages"]] == ["system", "user", "assistant", "user"]


def test_unreachable_endpoint_speaks_the_fallback():
    reply = _endpoint("http://127.0.0.1:9/v1/chat/completions", timeout_s=0.5).start("hello")
    assert wait_reply(reply) == [FALLBACK] and reply.error


def test_agent_speaks_the_endpoints_answer(chat_server, tmp_path):
    cfg = dialogue_cfg(responder={"kind": "openai", "url": chat_server})
    steps, transcript = run_component(cfg, np.concatenate([load_24k(LIBRIVOX), silence(5.0)]), tmp_path)
    agent = [t for t in transcript["turns"] if t["speaker"] == "agent"]
    assert agent and agent[0]["text"] == "Hello from the test server. It streams word by word!"
    assert [s.text_piece for s in steps if s.text_piece][:4] == ["Hello", "from", "the", "test"]
    sent = _ChatHandler.requests[0]["messages"][-1]["content"]
    assert "john" in sent and "consider" in sent  # the recognised user turn went to the endpoint


def test_endpoint_down_the_agent_says_so_and_does_not_crash(tmp_path):
    cfg = dialogue_cfg(responder={"kind": "openai", "url": "http://127.0.0.1:9/v1/chat/completions", "timeout_s": 0.5})
    steps, transcript = run_component(cfg, np.concatenate([load_24k(LIBRIVOX), silence(7.0)]), tmp_path)
    agent = [t for t in transcript["turns"] if t["speaker"] == "agent"]
    assert agent and agent[0]["text"] == FALLBACK and any(s.agent_speaking for s in steps)
