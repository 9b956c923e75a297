"""The comparison step of a reconstruction job (filled in by the analysis issue)."""


def compare_reconstructions(earlier, later):
    return None
