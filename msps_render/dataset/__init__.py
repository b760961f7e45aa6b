"""Datasets on disk: the shard schema (the only code that spells HDF5 keys), the shard
writer and reader, the typed manifest (`dataset.json`) and verification.

numpy-only at import (h5py is imported when a shard is opened), so the
training side can use it without the scene sampler or Mitsuba.
"""
from msps_render.dataset.digest import array_digest, file_digest
from msps_render.dataset.manifest import (MANIFEST, SHARD_DIR, Condition, Manifest, ShardEntry, load_manifest,
                                          new_manifest, read_manifest, shard_path, training_lights,
                                          write_manifest)
from msps_render.dataset.reader import (iter_whole_frames, open_shard, read_calibration, read_digests,
                                        read_frame_lambertian, read_frame_scenes, read_frame_table,
                                        read_patch_layout, read_patch_rows, read_patches, read_patches_into,
                                        read_shard_calibration,
                                        read_shard_patches, scene_is_lambertian, shard_errors,
                                        shard_summary)
from msps_render.dataset.schema import FORMAT_VERSION, FrameRecord, Patches, ShardContent, WholeFrame
from msps_render.dataset.verify import verify_dataset, verify_shard
from msps_render.dataset.writer import write_shard

__all__ = ["FORMAT_VERSION", "Patches", "FrameRecord", "ShardContent", "WholeFrame", "write_shard",
           "open_shard", "read_patches", "read_patches_into", "read_patch_layout", "read_calibration",
           "read_frame_lambertian", "scene_is_lambertian", "read_shard_patches", "read_shard_calibration",
           "read_frame_scenes", "read_frame_table", "read_patch_rows", "iter_whole_frames", "read_digests",
           "shard_summary", "shard_errors", "MANIFEST", "SHARD_DIR", "Manifest", "ShardEntry", "Condition",
           "load_manifest", "read_manifest", "write_manifest", "new_manifest", "shard_path", "training_lights", "verify_shard",
           "verify_dataset", "array_digest", "file_digest"]
