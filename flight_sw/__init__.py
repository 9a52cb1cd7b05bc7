"""Flight software: SfM hazard detection from two descent images (thesis ch. 3-4)."""
