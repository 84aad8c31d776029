"""The one OpenAI-compatible chat-completions client (Ollama, vLLM, llama.cpp server, hosted APIs),
shared by the LLM task proposer and the VLM explorer, over httpx (no SDK to pin for a single POST).

Messages are passed through as given, so multimodal content (a list of {"type": "text"} and
{"type": "image_url"} parts) works like plain strings. Each failed request is classified, so a
caller can count timeouts apart from server errors, refused connections and malformed replies.
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from typing import Any, Literal

import httpx

from schemas.config import ChatEndpointConfig
from schemas.errors import Sim2ActError
from schemas.retry import retrying

Failure = Literal["timeout", "http_error", "unreachable", "malformed"]


class ChatUnavailable(Sim2ActError, RuntimeError):
    """No usable answer: the endpoint stayed unreachable, refused the request, or broke the protocol.
    A known failure (one line from `sim2act`), raised in rollout workers too: it pickles whole."""

    def __init__(self, message: str, failures: list[Failure], refused: bool = False):
        super().__init__(message)
        self.failures = failures  # one per failed request, in order; the last is why it gave up
        self.refused = refused  # the server answered a 4xx that is not worth another try: the request is wrong

    def __reduce__(self):
        return type(self), (str(self), self.failures, self.refused)


@dataclass
class ChatReply:
    content: str  # the answer's message content
    failures: list[Failure] = field(default_factory=list)  # the failed requests retried before it


def _classify(exc: Exception) -> tuple[Failure, str]:
    if isinstance(exc, httpx.HTTPStatusError):
        return "http_error", f"HTTP {exc.response.status_code}"
    if isinstance(exc, httpx.TimeoutException):
        return "timeout", "timed out"
    return "unreachable", str(exc) or type(exc).__name__


def _transient(exc: BaseException) -> bool:
    """Worth another try: a timeout, a refused or dropped connection, a 5xx, a 408 or 429 (the server's
    timeout and rate limit). Not another 4xx (the request itself is wrong) nor a malformed reply (the
    server does not speak the protocol)."""
    if isinstance(exc, httpx.HTTPStatusError):
        return exc.response.status_code >= 500 or exc.response.status_code in (408, 429)
    return isinstance(exc, httpx.TransportError)


def complete(
    config: ChatEndpointConfig, messages: list[dict[str, Any]], *, who: str = "chat endpoint",
    max_tokens: int | None = None,
) -> ChatReply:
    """One JSON-mode chat completion over HTTP (httpx); retries what `_transient` says, waiting 1, 2,
    4 s ... (at most 10) between tries. `who` names the caller in errors."""
    payload: dict[str, Any] = {"model": config.model, "messages": messages, "temperature": config.temperature,
                               "response_format": {"type": "json_object"}}
    if max_tokens is not None:
        payload["max_tokens"] = max_tokens
    headers = {}
    if config.api_key_env and os.environ.get(config.api_key_env):
        headers["Authorization"] = f"Bearer {os.environ[config.api_key_env]}"
    url = config.url.rstrip("/") + "/chat/completions"
    failures: list[Failure] = []

    def post(client: httpx.Client) -> httpx.Response:
        try:
            return client.post(url, json=payload, headers=headers).raise_for_status()
        except (httpx.HTTPStatusError, httpx.TransportError) as exc:
            failures.append(_classify(exc)[0])
            raise

    with httpx.Client(timeout=config.timeout_s) as client:
        try:
            response = retrying(_transient, attempts=config.retries + 1, wait_s=1.0, backoff_max_s=10.0)(post, client)
        except (httpx.HTTPStatusError, httpx.TransportError) as exc:
            refused = isinstance(exc, httpx.HTTPStatusError) and not _transient(exc)
            raise ChatUnavailable(f"{who} at {url} did not answer ({_classify(exc)[1]}) after {len(failures)} tries",
                                  failures, refused) from None
    try:
        content = response.json()["choices"][0]["message"]["content"]
    except (KeyError, IndexError, TypeError, ValueError):  # JSONDecodeError, UnicodeDecodeError
        content = None
    if not isinstance(content, str):
        raise ChatUnavailable(f"{who} at {url} answered, but not in the chat-completions format", [*failures, "malformed"])
    return ChatReply(content, failures)
