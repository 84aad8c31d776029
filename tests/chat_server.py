"""A local HTTP server speaking the OpenAI chat-completions protocol with scripted replies: the
real protocol for the clients that talk to remote LLMs (task proposer, VLM explorer)."""

from __future__ import annotations

import json
import socket
import threading
from collections import deque
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

Reply = tuple[str | None, int, float]  # (content, HTTP status, delay in seconds)


class ScriptedServer(ThreadingHTTPServer):
    """Answers POST /v1/chat/completions with the script's replies in order, the last one again
    and again; content None sends a body that is not a chat completion. Records (path, headers,
    body) of every request."""

    def __init__(self, script: list[Reply]):
        super().__init__(("127.0.0.1", 0), _Handler)
        self.script, self.requests = deque(script), []

    @property
    def url(self) -> str:
        return f"http://127.0.0.1:{self.server_port}/v1"

    def next_reply(self) -> Reply:
        return self.script.popleft() if len(self.script) > 1 else self.script[0]


class _Handler(BaseHTTPRequestHandler):
    def do_POST(self):  # noqa: N802 (http.server's name)
        body = json.loads(self.rfile.read(int(self.headers["Content-Length"])))
        self.server.requests.append((self.path, dict(self.headers), body))
        content, status, delay = self.server.next_reply()
        threading.Event().wait(delay)
        reply = {"id": "chatcmpl-1", "object": "chat.completion", "model": body["model"],
                 "choices": [{"index": 0, "finish_reason": "stop",
                              "message": {"role": "assistant", "content": content}}]}
        data = json.dumps(reply if content is not None else {"error": "not a completion"}).encode()
        try:
            self.send_response(status)
            self.send_header("Content-Type", "application/json")
            self.send_header("Content-Length", str(len(data)))
            self.end_headers()
            self.wfile.write(data)
        except (BrokenPipeError, ConnectionResetError):  # the client timed out and left
            pass

    def log_message(self, *args):
        pass


def closed_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]
