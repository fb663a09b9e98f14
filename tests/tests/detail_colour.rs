//! The client accepts a detail planet's deep colour tree: every record of
//! both trees loaded and split through `PartialTree` (the linked-trees
//! binding of thesis §4.4.1 checked at each colour split), then merged back.

use planet_client::tree::{decode_record, Blocked, PartialTree};
use planet_core::format::{DbFile, Tree};
use planet_core::BlockId;
use std::sync::Arc;

/// Load LOD 0 of every leaf of `kind` and split it while it has children;
/// returns the blocks that split.
fn expand(tree: &mut PartialTree, db: &DbFile, kind: Tree) -> Vec<BlockId> {
    let mut split = Vec::new();
    loop {
        let leaves: Vec<BlockId> = tree
            .tree(kind)
            .unwrap()
            .nodes()
            .filter(|n| !n.split && n.lod == 1)
            .map(|n| n.id)
            .collect();
        if leaves.is_empty() {
            return split;
        }
        for id in leaves {
            let n = tree.tree(kind).unwrap().get(&id).unwrap();
            let width = tree.tree(kind).unwrap().width;
            let bytes = db.read_record(&n.record).unwrap();
            let first = tree.first_lod(kind, &id).unwrap();
            let codec = tree.tree(kind).unwrap().codec;
            let d = decode_record(kind, id, width, codec, &bytes, first).unwrap();
            let has_children = !d.children.is_empty();
            assert!(tree.apply_refine(d));
            if has_children {
                tree.split(kind, &id).unwrap();
                split.push(id);
            }
        }
    }
}

#[test]
fn client_loads_the_deep_colour_tree_with_its_binding() {
    let dir = tempfile::tempdir().unwrap();
    let path = dir.path().join("d.db");
    planet_testkit::harness::build_procedural_db_with_detail(
        &path,
        2,
        5,
        &["45,0,300,6".parse().unwrap()],
    )
    .unwrap();
    let db = DbFile::open(&path).unwrap();
    let header = Arc::new(db.header.clone());
    assert_eq!(header.colour.as_ref().unwrap().max_level, 6);
    let mut tree = PartialTree::new(header).unwrap();
    // Colour cannot split before the elevation block of its id has.
    let root = tree.colour().unwrap().nodes().next().unwrap().id;
    let bytes = db
        .read_record(&tree.colour().unwrap().get(&root).unwrap().record)
        .unwrap();
    let first = tree.first_lod(Tree::Colour, &root).unwrap();
    let codec = tree.colour().unwrap().codec;
    let d = decode_record(Tree::Colour, root, 128, codec, &bytes, first).unwrap();
    assert!(tree.apply_refine(d));
    assert_eq!(tree.split(Tree::Colour, &root), Err(Blocked::Binding));
    let esplit = expand(&mut tree, &db, Tree::Elevation);
    let csplit = expand(&mut tree, &db, Tree::Colour);
    tree.validate().unwrap();
    let colour = tree.colour().unwrap();
    let elevation = tree.elevation();
    assert_eq!(elevation.max_level, 6);
    // The colour tree reached the region's level, and is bound: every colour
    // node has the elevation node of its id.
    assert!(colour.nodes().any(|n| n.id.level == 6));
    assert!(colour.nodes().all(|n| elevation.get(&n.id).is_some()));
    // Deeper than the base level 2 only where the elevation is.
    let deep_colour = csplit.iter().filter(|b| b.level >= 2).count();
    assert!(deep_colour >= 4, "{deep_colour}");
    assert!(csplit.len() <= esplit.len());
    // An elevation block under a split colour block cannot merge; after the
    // colour merges, it can.
    let b = *csplit.iter().max_by_key(|b| b.level).unwrap();
    assert_eq!(tree.can_merge(Tree::Elevation, &b), Err(Blocked::Binding));
    tree.merge(Tree::Colour, &b).unwrap();
    tree.merge(Tree::Elevation, &b).unwrap();
    tree.validate().unwrap();
}
