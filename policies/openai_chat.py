"""The one OpenAI-compatible chat-completions client (Ollama, vLLM, llama.cpp server, hosted APIs),
shared by the LLM task proposer and the VLM explorer. Plain urllib: no SDK to pin for a single POST.

Messages are passed through as given, so multimodal content (a list of {"type": "text"} and
{"type": "image_url"} parts) works like plain strings. Each failed request is classified, so a
caller can count timeouts apart from server errors, refused connections and malformed replies.
"""

from __future__ import annotations

import http.client
import json
import os
import time
import urllib.error
import urllib.request
from dataclasses import dataclass, field
from typing import Any, Literal

from schemas.config import ChatEndpointConfig

Failure = Literal["timeout", "http_error", "unreachable", "malformed"]


class ChatUnavailable(RuntimeError):
    """No usable answer: the endpoint stayed unreachable, refused the request, or broke the protocol."""

    def __init__(self, message: str, failures: list[Failure]):
        super().__init__(message)
        self.failures = failures  # one per failed request, in order; the last is why it gave up


@dataclass
class ChatReply:
    content: str  # the answer's message content
    failures: list[Failure] = field(default_factory=list)  # the failed requests retried before it


def _classify(exc: Exception) -> tuple[Failure, str]:
    if isinstance(exc, urllib.error.HTTPError):
        return "http_error", f"HTTP {exc.code}"
    reason = getattr(exc, "reason", exc)  # URLError wraps the socket error
    if isinstance(reason, TimeoutError):
        return "timeout", "timed out"
    return "unreachable", str(reason)


def complete(
    config: ChatEndpointConfig, messages: list[dict[str, Any]], *, who: str = "chat endpoint",
    max_tokens: int | None = None,
) -> ChatReply:
    """One JSON-mode chat completion; retries timeouts, refused connections and 5xx (not 4xx: the
    request itself is wrong, nor malformed replies: the server does not speak the protocol).
    `who` names the caller in errors."""
    payload: dict[str, Any] = {"model": config.model, "messages": messages, "temperature": config.temperature,
                               "response_format": {"type": "json_object"}}
    if max_tokens is not None:
        payload["max_tokens"] = max_tokens
    body = json.dumps(payload).encode()
    headers = {"Content-Type": "application/json"}
    if config.api_key_env and os.environ.get(config.api_key_env):
        headers["Authorization"] = f"Bearer {os.environ[config.api_key_env]}"
    url = config.url.rstrip("/") + "/chat/completions"
    failures: list[Failure] = []
    last_error = ""
    for attempt in range(config.retries + 1):
        request = urllib.request.Request(url, data=body, headers=headers, method="POST")
        try:
            with urllib.request.urlopen(request, timeout=config.timeout_s) as response:
                raw = response.read()
        except (urllib.error.URLError, TimeoutError, ConnectionError, http.client.HTTPException) as exc:
            kind, last_error = _classify(exc)
            failures.append(kind)
            if isinstance(exc, urllib.error.HTTPError) and exc.code < 500:
                break
        else:
            try:
                content = json.loads(raw)["choices"][0]["message"]["content"]
            except (KeyError, IndexError, TypeError, ValueError):  # JSONDecodeError, UnicodeDecodeError
                content = None
            if not isinstance(content, str):
                raise ChatUnavailable(f"{who} at {url} answered, but not in the chat-completions format",
                                      [*failures, "malformed"])
            return ChatReply(content, failures)
        if attempt < config.retries:
            time.sleep(min(2.0**attempt, 10.0))
    raise ChatUnavailable(f"{who} at {url} did not answer ({last_error}) after {len(failures)} tries", failures)
