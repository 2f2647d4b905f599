"""The scene bundle, format ``panogs-scene/1`` (docs/scene_format.md): reader, validation, writer and archives."""
