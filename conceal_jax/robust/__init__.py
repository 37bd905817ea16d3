"""Layer 5: what an owner's mark must survive and how ownership is decided: attacks on the check render
and on the shared scene. Imports every layer below."""
