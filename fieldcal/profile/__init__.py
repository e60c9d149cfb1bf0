"""The lens profile (``fieldcal-profile/1``): what a calibration found, with its uncertainty and evidence."""

from fieldcal.profile.lens_profile import LensProfile, load_profile_or_truth

__all__ = ["LensProfile", "load_profile_or_truth"]
