"""Dataset readers (7-Scenes, synthetic) producing :class:`lipmap.scene.Scene`."""
