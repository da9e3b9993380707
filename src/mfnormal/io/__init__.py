"""Input and output: XML scenes and glTF models in, EXR and PNG images out, and the checks of every
input (a scene, a file, an argument) that run before any long work starts."""
