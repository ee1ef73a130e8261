"""Separate pieces of a reading set aside: blocks of bone and dural venous sinuses (issue 41)."""

import numpy as np
from scipy import ndimage

from dsareg_engine.io.bone_plates import BONE_CONTACT_SHARE
from dsareg_engine.io.separate_pieces import PiecesSetAside, without_pieces
from dsareg_engine.io.venous_sinuses import ALONG_BONE_SHARE


def _tube_block_and_bone():
    """A vessel (a bent tube) in tissue touching bone along a stretch (its canal), a block of cancellous bone inside
    a cortical shell, and the shell: the mask read as vessels and what bone is there."""
    mask = np.zeros((60, 60, 60), bool)
    mask[10:50, 10:13, 10:13] = True  # the tube's trunk
    mask[47:50, 10:40, 10:13] = True  # a branch
    bone = np.zeros(mask.shape, bool)
    bone[20:30, 9, 9:14] = bone[20:30, 13, 9:14] = True  # the canal: a stretch of the trunk between two walls
    bone[30:46, 30:46, 30:46] = True  # the cortical shell (its inside is the block)
    bone[32:44, 32:44, 32:44] = False
    mask[32:44, 32:44, 32:44] = True  # the block, all of it in the vessels' window
    return mask, bone


def test_a_separate_piece_inside_bone_is_set_aside_and_the_tree_kept():
    spacing = np.ones(3)  # the block: 1,728 mm³
    mask, bone = _tube_block_and_bone()
    kept, records = without_pieces(mask, spacing, lambda box: bone[box])
    pieces = records["bone"]
    assert pieces.count == 1 and not kept[32:44, 32:44, 32:44].any() and pieces.set_aside[32:44, 32:44, 32:44].all()
    assert np.array_equal(kept, mask & ~pieces.set_aside) and kept[10:50, 10:13, 10:13].all()
    assert 0.0 < pieces.nearest_share < BONE_CONTACT_SHARE  # the tree's share, the nearer to the threshold
    assert records["sinuses"].count == 0 and records["sinuses"].set_aside is None
    tree_only = mask.copy()
    tree_only[32:44, 32:44, 32:44] = False
    same, none = without_pieces(tree_only, spacing, lambda box: bone[box])  # one piece: nothing to decide
    assert same is tree_only and none["bone"].count == 0 and none["bone"].nearest_share is None
    small = tree_only.copy()
    small[2:5, 2:5, 2:5] = True  # a 27-mm³ piece in bone, not bone-sized: it stays
    cavity = bone.copy()
    cavity[1:6, 1:6, 1:6] = True
    cavity[2:5, 2:5, 2:5] = False
    same, none = without_pieces(small, spacing, lambda box: cavity[box])
    assert same is small and none["bone"].count == 0 and none["bone"].nearest_share < BONE_CONTACT_SHARE
    block_only = mask & ~tree_only
    block_only[10:20, 50:53, 50:53] = True  # a second piece, in tissue: the block goes, it stays
    kept, records = without_pieces(block_only, spacing, lambda box: bone[box])
    assert records["bone"].count == 1 and kept[10:20, 50:53, 50:53].all() and not kept[32:44, 32:44, 32:44].any()
    two_blocks = mask & ~tree_only
    two_blocks[2:14, 2:14, 2:14] = True
    enclosing = bone.copy()
    enclosing[1:15, 1:15, 1:15] = True
    enclosing[2:14, 2:14, 2:14] = False
    kept, records = without_pieces(two_blocks, spacing, lambda box: enclosing[box])  # every piece in bone: kept
    assert kept is two_blocks and records["bone"].count == 0
    assert records["bone"].nearest_share is None  # thick and along bone: their surface's share decides nothing


def _vault_sinus_and_tree(sinus_radius: float):
    """A skull (a spherical shell of bone, inner radius 40 voxels), a tube of ``sinus_radius`` voxels whose lumen lies
    against its inner table along a half circle (a superior sagittal sinus), and a vessel tree in the middle (a
    trunk through a canal in a skull-base plate, two branches): the mask read as vessels and the bone."""
    n = 100
    z, y, x = np.ogrid[:n, :n, :n]
    centre = (n - 1) / 2.0
    r = np.sqrt((z - centre) ** 2 + (y - centre) ** 2 + (x - centre) ** 2)
    bone = (r >= 40) & (r < 45)
    plate = (z >= 20) & (z < 26) & (r < 40)  # the skull base
    bone |= plate
    in_yz = np.sqrt((z - centre) ** 2 + (x - centre) ** 2)  # the sinus: in the midline plane y = centre, above z
    sinus = (np.sqrt((in_yz - (40 - sinus_radius)) ** 2 + (y - centre) ** 2) <= sinus_radius) & (z > centre)
    tree = np.zeros((n, n, n), bool)
    tree[12:60, 48:52, 48:52] = True  # the trunk, up through the plate (its canal)
    tree[56:60, 30:52, 48:52] = True
    tree[56:60, 48:70, 48:52] = True
    bone &= ~tree
    bone[20:26, 47, 47:53] = bone[20:26, 52, 47:53] = True  # the canal's walls
    bone &= ~tree
    return sinus | tree, bone, sinus, tree


def test_a_sinus_along_the_inner_table_is_set_aside_and_the_tree_kept():
    spacing = np.full(3, 0.5)
    mask, bone, sinus, tree = _vault_sinus_and_tree(sinus_radius=6.0)  # 3 mm: a sinus's lumen
    assert not (ndimage.binary_dilation(sinus) & tree).any()
    kept, records = without_pieces(mask, spacing, lambda box: bone[box])
    found = records["sinuses"]
    assert found.count == 1 and np.array_equal(found.set_aside, sinus) and np.array_equal(kept, tree)
    assert found.set_aside_shares[0] > 0.9  # along bone for its whole course
    assert found.kept_shares == ()  # the tree is too thin for a sinus: not judged by this measure
    assert records["bone"].count == 0  # the sinus touches bone on one side only: no block of bone
    assert records["bone"].nearest_share < BONE_CONTACT_SHARE  # (the tree's: the sinus is no close call of it)


def test_a_thin_tube_along_bone_is_no_sinus_and_a_lone_sinus_stays():
    spacing = np.full(3, 0.5)
    mask, bone, _, _ = _vault_sinus_and_tree(sinus_radius=2.0)  # 1 mm: a vessel's, too thin for a sinus
    kept, records = without_pieces(mask, spacing, lambda box: bone[box])
    assert kept is mask and records["sinuses"].count == 0 and records["sinuses"].nearest_share is None
    _, bone, sinus, _ = _vault_sinus_and_tree(sinus_radius=6.0)
    kept, records = without_pieces(sinus, spacing, lambda box: bone[box])  # one piece: nothing to decide
    assert kept is sinus and records["sinuses"].count == 0
    two = sinus.copy()
    two[:, :, 45:55] = False  # two arcs, each along bone
    assert ndimage.label(two)[1] == 2
    kept, records = without_pieces(two, spacing, lambda box: bone[box])
    assert kept is two and records["sinuses"].count == 0  # every piece would go: the reading is judged as it is
    assert min(records["sinuses"].kept_shares) > ALONG_BONE_SHARE
    speck = two.copy()
    speck[2:4, 2:4, 2:4] = True  # and a speck: next to nothing would stay
    kept, records = without_pieces(speck, spacing, lambda box: bone[box])
    assert kept is speck and records["sinuses"].count == 0


def test_a_record_followed_by_a_later_reading_s():
    first = PiecesSetAside(ALONG_BONE_SHARE, 1, np.ones(3, bool), (0.1,), (0.98,))
    later = PiecesSetAside(ALONG_BONE_SHARE, 0, None, (0.15,), ())
    both = first.then(later)
    assert both.count == 1 and both.set_aside is None and both.kept_shares == (0.15,)
    assert both.set_aside_shares == (0.98,) and both.nearest_share == 0.98  # the later reading's 0.15 is further
    assert PiecesSetAside(ALONG_BONE_SHARE).nearest_share is None


def test_a_vessel_whose_trunk_runs_in_bone_is_not_a_block_of_bone():
    """A small tree whose trunk lies in a bony canal for much of its length has most of its surface against bone
    (as a block's is), but its medial axis leaves the bone: it stays beside another piece."""
    spacing = np.ones(3)
    mask = np.zeros((70, 40, 40), bool)
    mask[5:65, 18:23, 18:23] = True  # a vessel 60 mm long, 5 mm across
    bone = np.zeros(mask.shape, bool)
    bone[5:38, 16:25, 16:25] = True  # a canal around 33 mm of it (55 %)
    bone &= ~mask
    mask[10:20, 2:12, 30:38] = True  # another piece, in tissue (800 mm³)
    kept, records = without_pieces(mask, spacing, lambda box: bone[box])
    assert kept is mask and records["bone"].count == 0 and records["sinuses"].count == 0
    assert max(records["bone"].kept_shares) >= BONE_CONTACT_SHARE  # in bone by its surface alone
