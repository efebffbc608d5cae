"""The scene files shipped with tcspc-lidar (TOML; docs/simulator.md describes the keys).

A package only so that a wheel carries them: installed, ``scenes/`` sits beside
``pipeline/`` and ``flows/`` exactly as in a checkout, so ``tcspc demo`` and the campaigns
find ``scenes/street.toml`` the same way in both.
"""
