"""A verifier that asks any OpenAI-compatible chat-completions endpoint (OpenAI, Ollama, vLLM, ...).

The crop goes as a base64 JPEG `image_url` part beside the task text. 429 and 5xx replies and dropped
connections are retried with exponential backoff inside the time budget; the API key comes from an
environment variable named in the configuration, never from a file.
"""

from __future__ import annotations

import base64
import os
import threading
import time

import cv2
import numpy as np
import requests

from backend.images import encode_jpeg
from backend.verifiers.answer_parser import parse_answer
from backend.verifiers.interface import VerifierAnswer, VerifierError, VerifierTimeout
from backend.verifiers.prompts import PROMPT_SETS, family_for, render

RETRYABLE = {408, 409, 425, 429, 500, 502, 503, 504}


class OpenAIChatVerifier:
    def __init__(
        self,
        base_url: str,
        model: str,
        api_key_env: str = "OPENAI_API_KEY",
        prompt_family: str = "auto",
        max_retries: int = 2,
        backoff_s: float = 0.5,
        max_tokens: int = 200,
        crop_max_side: int = 512,
        jpeg_quality: int = 90,
    ) -> None:
        self.url = base_url.rstrip("/") + "/chat/completions"
        self.model = model
        self.name = f"vlm:{model}"
        self.prompt_set = PROMPT_SETS[family_for(model, prompt_family)]
        self.api_key = os.environ.get(api_key_env, "")
        self.max_retries = max_retries
        self.backoff_s = backoff_s
        self.max_tokens = max_tokens
        self.crop_max_side = crop_max_side
        self.jpeg_quality = jpeg_quality
        self._local = threading.local()  # one requests.Session per worker thread

    def _session(self) -> requests.Session:
        session = getattr(self._local, "session", None)
        if session is None:
            session = self._local.session = requests.Session()
        return session

    def request_body(self, crop_bgr: np.ndarray, prompt: str, superset: str) -> dict[str, object]:
        height, width = crop_bgr.shape[:2]
        scale = min(1.0, self.crop_max_side / max(height, width))
        if scale < 1.0:
            crop_bgr = cv2.resize(
                crop_bgr,
                (max(1, round(width * scale)), max(1, round(height * scale))),
                interpolation=cv2.INTER_AREA,
            )
        data_url = (
            "data:image/jpeg;base64," + base64.b64encode(encode_jpeg(crop_bgr, self.jpeg_quality)).decode()
        )
        system, task = render(self.prompt_set, prompt, superset)
        messages: list[dict[str, object]] = [{"role": "system", "content": system}] if system else []
        messages.append(
            {
                "role": "user",
                "content": [
                    {"type": "text", "text": task},
                    {"type": "image_url", "image_url": {"url": data_url}},
                ],
            }
        )
        return {"model": self.model, "messages": messages, "max_tokens": self.max_tokens, "temperature": 0}

    def verify(
        self,
        crop_bgr: np.ndarray,
        target_box: tuple[float, float, float, float],
        prompt: str,
        superset: str,
        timeout_s: float,
    ) -> VerifierAnswer:
        body = self.request_body(crop_bgr, prompt, superset)
        headers = {"Authorization": f"Bearer {self.api_key}"} if self.api_key else {}
        deadline = time.monotonic() + timeout_s
        attempt = 0
        while True:
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                raise VerifierTimeout(f"{self.model}: no answer within {timeout_s:.1f} s")
            try:
                response = self._session().post(self.url, json=body, headers=headers, timeout=remaining)
            except requests.Timeout as exc:
                raise VerifierTimeout(f"{self.model}: no answer within {timeout_s:.1f} s") from exc
            except requests.ConnectionError as exc:
                status, reason, retry_after = None, f"connection failed: {exc}", None
            else:
                if response.status_code == 200:
                    return self._answer(response)
                status, reason = response.status_code, response.text[:200]
                retry_after = response.headers.get("Retry-After")
                if status not in RETRYABLE:
                    raise VerifierError(f"{self.model}: HTTP {status}: {reason}")
            if attempt >= self.max_retries:
                raise VerifierError(
                    f"{self.model}: gave up after {attempt + 1} attempts: HTTP {status}: {reason}"
                )
            delay = self.backoff_s * (2**attempt)
            if retry_after and retry_after.replace(".", "", 1).isdigit():
                delay = max(delay, float(retry_after))
            if time.monotonic() + delay >= deadline:
                raise VerifierTimeout(
                    f"{self.model}: HTTP {status}, no time left to retry within {timeout_s:.1f} s"
                )
            time.sleep(delay)
            attempt += 1

    def _answer(self, response: requests.Response) -> VerifierAnswer:
        try:
            content = response.json()["choices"][0]["message"]["content"]
        except (ValueError, KeyError, IndexError, TypeError) as exc:
            raise VerifierError(
                f"{self.model}: reply is not a chat completion: {response.text[:200]}"
            ) from exc
        if isinstance(content, list):  # some servers return content parts
            content = " ".join(str(p.get("text", "")) for p in content if isinstance(p, dict))
        verdict, justification = parse_answer(str(content or ""))
        return VerifierAnswer(verdict, justification, self.name)
