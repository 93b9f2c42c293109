"""The environments: one module each, composing sim/ and perception/ with a reward."""
