"""What a simplification costs, measured: a Warp 3DGS renderer (``render``), cameras that frame a
scene or come from a trainer (``cameras``), image metrics (``metrics``), the comparison of scenes
over views (``evaluate``) and the text of its contact sheets (``glyphs``).

Importing this package loads nothing: each module is imported where it is used.
"""
