"""meniscope's offline half: synthetic training sets, model training and export.

May import ``service`` (scene, physics, renderer, camera model) and adds torch where models are
trained; ``service`` never imports ``training``.
"""
