"""Building the configured verifier (`[verifier] kind`): none, local, local-hsv, vlm or cascade."""

from __future__ import annotations

from backend.config import VerifierConfig, VlmConfig
from backend.verifiers.attributes import AttributeVerifier
from backend.verifiers.cascade import CascadeVerifier
from backend.verifiers.interface import Verifier
from backend.verifiers.openai_chat import OpenAIChatVerifier
from backend.verifiers.person_model import PersonModel
from backend.verifiers.person_verifier import PersonVerifier


def build_verifier(verifier: VerifierConfig, vlm: VlmConfig) -> Verifier | None:
    """The verifier for `verifier.kind`; None for "none" (detector only).

    "local" is the person-model verifier (needs the `person` extra and its model file, and says how to
    install them when they are missing); "local-hsv" the older box-fraction colour rules, for comparison.
    """
    if verifier.kind == "none":
        return None
    if verifier.kind == "local":
        return PersonVerifier(PersonModel(instances=verifier.local_instances))
    if verifier.kind == "local-hsv":
        return AttributeVerifier()
    chat = OpenAIChatVerifier(
        vlm.base_url,
        vlm.model,
        vlm.api_key_env,
        vlm.prompt_family,
        vlm.max_retries,
        vlm.backoff_s,
        vlm.max_tokens,
        vlm.crop_max_side,
        vlm.jpeg_quality,
    )
    if verifier.kind == "vlm":
        return chat
    return CascadeVerifier(PersonVerifier(PersonModel(instances=verifier.local_instances)), chat)
