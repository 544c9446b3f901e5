"""The padding rule that lets arrays of similar lengths share one compiled program."""


def bucket(n: int) -> int:
    """The length an axis of `n` entries is padded to (the next power of two, at least 16):
    save grids, a fit's records and a map stage's members, so that lengths in one bucket share
    one compilation, at most half of it padding."""
    return max(16, 1 << (int(n) - 1).bit_length())
