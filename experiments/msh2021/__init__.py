"""The December 2021 Mount St. Helens landslide, calibrated and diagnosed from its surveyed elevation change."""
