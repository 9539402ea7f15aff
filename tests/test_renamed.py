"""The old names of the many-at-once classes still import, as the renamed class, with a
DeprecationWarning that names the new one (docs/architecture.md, one word: Batch)."""

import importlib

import pytest

RENAMED = [
    ("spindle.chain.batch", "BatchedArmChain", "ArmChainBatch"),
    ("spindle.native.chain", "CBatchedArmChain", "CArmChainBatch"),
    ("spindle.native.spindle", "SpindleBatch", "CSpindleBatch"),
    ("proprio_env.body.encoder", "EncoderBank", "EncoderBatch"),
    ("proprio_env.encoder", "EncoderBank", "EncoderBatch"),
    ("spindle.chain.driver", "SpindleBank", "SpindleDriver"),
    ("spindle.chain.bank", "SpindleBank", "SpindleDriver"),
    ("proprio_env.wrappers", "SpindleBank", "SpindleDriver"),
    ("proprio_env.wrappers.bank", "SpindleBank", "SpindleDriver"),
]


@pytest.mark.parametrize("module, old, new", RENAMED)
def test_an_old_name_is_the_renamed_class_with_a_warning(module, old, new):
    mod = importlib.import_module(module)
    with pytest.warns(DeprecationWarning, match=new):
        cls = getattr(mod, old)
    assert cls is getattr(mod, new)
    assert cls.__name__ == new


@pytest.mark.parametrize("module", sorted({m for m, _, _ in RENAMED}))
def test_a_name_never_defined_is_still_an_attribute_error(module):
    mod = importlib.import_module(module)
    with pytest.raises(AttributeError, match="NoSuchThing"):
        mod.NoSuchThing  # noqa: B018
