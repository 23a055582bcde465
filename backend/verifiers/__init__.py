"""Verifiers: does this crop show the full description? (VLM over HTTP, the local attribute check, both.)"""

from backend.verifiers.interface import Verifier, VerifierAnswer, VerifierError, VerifierTimeout

__all__ = ["Verifier", "VerifierAnswer", "VerifierError", "VerifierTimeout"]
