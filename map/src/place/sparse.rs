//! The place grid's levels stored sparsely. Space is cut into blocks of 8^3 voxels
//! (512 bits, 8 words: one cache line per level); only blocks holding a marked voxel
//! at some level exist. Levels grow with their number (a level-`l` cube holds the
//! level-`(l-1)` cube at the same corner), so a block is empty below some level `e`,
//! wholly marked from some level `f` on (the inside of the upper levels, which
//! dilation fills), and partly marked in between: one table entry per block gives
//! `e`, `f` and where the bits of its partly marked levels are. The entries are found
//! through a dense directory over the grid's blocks when that costs at most
//! [`DIRECTORY_RATIO`] entries per block kept (a compact site: one load, as fast as
//! dense bits), else through an open-addressing hash table (linear probing, at most
//! half full: memory in proportion to the blocks kept however wide the site). Both
//! are plain arrays, so a baked grid is read in place.
//!
//! A block's bits: word `z`, bit `x + 8 y` (local coordinates 0..8).

use rustc_hash::FxHashMap as HashMap;

/// Voxels per block edge.
pub const BLOCK_EDGE: i64 = 8;
/// Words per block and level.
pub const BLOCK_WORDS: usize = 8;
/// A free table slot's key (block coordinates never reach it).
pub const EMPTY_KEY: u64 = u64::MAX;
/// Bits of a block coordinate in a key.
const AXIS_BITS: u32 = 20;
/// Most voxels along one axis a grid may span (block coordinates fit their key field).
pub const MAX_EXTENT: u64 = (1 << AXIS_BITS) * BLOCK_EDGE as u64;
/// Most partly marked block levels a table entry can point at.
pub const MAX_STORED: u64 = 1 << 24;
/// The directory is used while it holds at most this many slots per block kept (16
/// slots, 64 bytes: one block level's bits).
pub const DIRECTORY_RATIO: u64 = 16;
/// Block levels stored first in the bits: all clear, then all set, so a lookup reads
/// a word whatever the block's state at that level.
pub const ZERO_BLOCK: usize = 0;
/// See [`ZERO_BLOCK`].
pub const ONES_BLOCK: usize = 1;
/// The entry of a block empty at every level (in the directory).
pub const ABSENT: u32 = (15 << 4) | 15;

type Bits = [u64; BLOCK_WORDS];

/// The table key of block `b` (coordinates in `[0, 2^20)`).
#[inline]
pub fn key(b: [i64; 3]) -> u64 {
    ((b[2] as u64) << (2 * AXIS_BITS)) | ((b[1] as u64) << AXIS_BITS) | b[0] as u64
}

/// Block coordinates of a key.
pub fn unkey(key: u64) -> [i64; 3] {
    let field = |shift: u32| ((key >> shift) & ((1 << AXIS_BITS) - 1)) as i64;
    [field(0), field(AXIS_BITS), field(2 * AXIS_BITS)]
}

/// A table entry's value: the block is empty at levels below `first`, wholly marked
/// from `full` on, and the bits of level `l` in between are block `base + l - first`
/// of the bits.
#[inline]
pub fn entry(base: u32, first: usize, full: usize) -> u32 {
    (base << 8) | ((first as u32) << 4) | full as u32
}

/// `(base, first, full)` of an entry.
#[inline]
pub fn unentry(entry: u32) -> (u32, usize, usize) {
    (
        entry >> 8,
        ((entry >> 4) & 15) as usize,
        (entry & 15) as usize,
    )
}

/// The home slot of `key` in a table of `1 << (64 - shift)` slots (Fibonacci hashing:
/// neighbouring blocks spread over the table).
#[inline]
pub fn home(key: u64, shift: u32) -> usize {
    (key.wrapping_mul(0x9E37_79B9_7F4A_7C15) >> shift) as usize
}

/// The hash shift of a table of `capacity` (a power of two, at least 2) slots.
pub fn shift_of(capacity: usize) -> u32 {
    64 - capacity.trailing_zeros()
}

/// A grid's levels, sparse: the directory, or the table (`keys`, `entries`), and the
/// bits of the block levels partly marked (`words`, [`BLOCK_WORDS`] per block and
/// level, after the [`ZERO_BLOCK`] and the [`ONES_BLOCK`]).
#[derive(Debug, Clone, PartialEq, Default)]
pub struct SparseLevels {
    /// The entry of every block of the grid (x fastest), [`ABSENT`] where none; empty
    /// when the table is used.
    pub directory: Vec<u32>,
    /// Block keys ([`key`]), [`EMPTY_KEY`] where free; a power-of-two length, or
    /// empty when the directory is used.
    pub keys: Vec<u64>,
    /// Per slot: the block's [`entry`].
    pub entries: Vec<u32>,
    /// Bits of the partly marked block levels.
    pub words: Vec<u64>,
}

/// Builds the levels over marked level-0 voxels (each coordinate in `[0, dims)`),
/// inside the grid only (voxel coordinates >= 0: a cube starting below the grid is
/// answered by the grid's first voxel, see [`crate::place::GridView::marked`]).
/// `max_blocks` bounds the blocks kept (the top level's); past it, `Err` gives the
/// blocks counted so far.
pub fn build(
    marked: &[[i64; 3]],
    dims: [i64; 3],
    levels: usize,
    max_blocks: u64,
) -> Result<SparseLevels, u64> {
    let mut level: HashMap<[i64; 3], Bits> = HashMap::default();
    for v in marked {
        let b = v.map(|c| c.div_euclid(BLOCK_EDGE));
        let [x, y, z] = v.map(|c| c.rem_euclid(BLOCK_EDGE));
        level.entry(b).or_insert([0; BLOCK_WORDS])[z as usize] |= 1 << (x + 8 * y);
    }
    let mut per_level: Vec<HashMap<[i64; 3], Bits>> = Vec::with_capacity(levels);
    for l in 0..levels {
        if l > 0 {
            let below = per_level.last().expect("level 0 is kept first");
            level = dilate(below, 0, 1 << (l - 1));
            for axis in 1..3 {
                level = dilate(&level, axis, 1 << (l - 1));
            }
        }
        if level.len() as u64 > max_blocks {
            return Err(level.len() as u64);
        }
        per_level.push(std::mem::take(&mut level));
    }
    // Every block of a level is one of the next level's: the top level's are all.
    let mut blocks: Vec<[i64; 3]> = per_level[levels - 1].keys().copied().collect();
    // z, y, x order: blocks near in space have their bits near in the file.
    blocks.sort_unstable_by_key(|b| [b[2], b[1], b[0]]);
    let block_dims = dims.map(|d| (d + BLOCK_EDGE - 1) / BLOCK_EDGE);
    let spanned = block_dims.iter().map(|&d| d as u64).product::<u64>();
    let dense = spanned <= DIRECTORY_RATIO * blocks.len() as u64;
    let capacity = (2 * blocks.len()).next_power_of_two().max(2);
    let shift = shift_of(capacity);
    let mut out = SparseLevels {
        directory: if dense {
            vec![ABSENT; spanned as usize]
        } else {
            Vec::new()
        },
        keys: if dense {
            Vec::new()
        } else {
            vec![EMPTY_KEY; capacity]
        },
        entries: if dense { Vec::new() } else { vec![0; capacity] },
        words: [[0; BLOCK_WORDS], [u64::MAX; BLOCK_WORDS]].concat(),
    };
    for b in blocks {
        // Voxels past the grid's end are never looked up: they count as marked, so
        // a block at the end can be wholly marked.
        let past = past_end(b, dims);
        let first = (0..levels)
            .find(|&l| per_level[l].contains_key(&b))
            .expect("the top level holds every block");
        let full = (first..levels)
            .find(|&l| {
                let bits = &per_level[l][&b];
                (0..BLOCK_WORDS).all(|w| bits[w] | past[w] == u64::MAX)
            })
            .unwrap_or(levels);
        let base = out.words.len() / BLOCK_WORDS;
        if (base + full - first) as u64 > MAX_STORED {
            return Err(MAX_STORED);
        }
        for bits in per_level.iter().take(full).skip(first) {
            out.words.extend_from_slice(&bits[&b]);
        }
        let value = entry(base as u32, first, full);
        if dense {
            out.directory[directory_index(b, block_dims)] = value;
            continue;
        }
        let k = key(b);
        let mut i = home(k, shift);
        while out.keys[i] != EMPTY_KEY {
            i = (i + 1) & (capacity - 1);
        }
        out.keys[i] = k;
        out.entries[i] = value;
    }
    Ok(out)
}

/// Block `b`'s slot in the directory of a grid of `block_dims` blocks.
#[inline]
pub fn directory_index(b: [i64; 3], block_dims: [i64; 3]) -> usize {
    (b[0] + block_dims[0] * (b[1] + block_dims[1] * b[2])) as usize
}

/// The block level holding a voxel's bit at `level` in the block whose entry is
/// `value`: the [`ZERO_BLOCK`] below its first level, the [`ONES_BLOCK`] from its
/// full level on.
#[inline]
pub fn block_at(value: u32, level: usize) -> usize {
    let (base, first, full) = unentry(value);
    if level < first {
        ZERO_BLOCK
    } else if level >= full {
        ONES_BLOCK
    } else {
        base as usize + level - first
    }
}

/// The bits of block `b`'s voxels at or past `dims` on some axis.
fn past_end(b: [i64; 3], dims: [i64; 3]) -> Bits {
    let mut bits = [0; BLOCK_WORDS];
    if (0..3).all(|a| (b[a] + 1) * BLOCK_EDGE <= dims[a]) {
        return bits;
    }
    for (z, word) in bits.iter_mut().enumerate() {
        for y in 0..8 {
            for x in 0..8 {
                let v = [x, y, z as i64];
                if (0..3).any(|a| b[a] * BLOCK_EDGE + v[a] >= dims[a]) {
                    *word |= 1 << (x + 8 * y);
                }
            }
        }
    }
    bits
}

/// Per-row masks of the low `k` bits of each 8-bit row of a word.
const fn row_mask(k: u32) -> u64 {
    0x0101_0101_0101_0101 * ((1_u64 << k) - 1)
}

/// Bits of block `b` at local coordinate `c + r` along `axis` (`r` in 1..8): from
/// `low` (block `b`) while `c + r < 8`, from `high` (the next block) beyond.
fn shifted(low: &Bits, high: &Bits, axis: usize, r: u32) -> Bits {
    let mut out = [0; BLOCK_WORDS];
    for (w, o) in out.iter_mut().enumerate() {
        *o = match axis {
            0 => ((low[w] >> r) & row_mask(8 - r)) | ((high[w] << (8 - r)) & !row_mask(8 - r)),
            1 => (low[w] >> (8 * r)) | (high[w] << (64 - 8 * r)),
            _ => {
                let z = w + r as usize;
                if z < BLOCK_WORDS {
                    low[z]
                } else {
                    high[z - BLOCK_WORDS]
                }
            }
        };
    }
    out
}

/// One doubling step along `axis`: voxel `v` also takes the mark of `v + h` (`h` a
/// power of two). Each block's bits are pushed to the blocks they mark (its own and
/// the one or two `h` below it): one table update each, no lookups of absent blocks.
fn dilate(src: &HashMap<[i64; 3], Bits>, axis: usize, h: i64) -> HashMap<[i64; 3], Bits> {
    let (q, r) = (h / BLOCK_EDGE, (h % BLOCK_EDGE) as u32);
    let zero = [0; BLOCK_WORDS];
    let along = |b: [i64; 3], d: i64| {
        let mut b = b;
        b[axis] += d;
        b
    };
    let mut out: HashMap<[i64; 3], Bits> =
        HashMap::with_capacity_and_hasher(src.len() * 2, Default::default());
    let mut mark = |b: [i64; 3], bits: Bits| {
        // Blocks below the grid's first voxel (which is a block corner) are not kept.
        if b.iter().all(|&c| c >= 0) && bits.iter().any(|&w| w != 0) {
            let kept = out.entry(b).or_insert(zero);
            for (k, w) in kept.iter_mut().zip(bits) {
                *k |= w;
            }
        }
    };
    for (&b, bits) in src {
        mark(b, *bits);
        if r == 0 {
            mark(along(b, -q), *bits);
        } else {
            // The block `q` below sees these bits shifted down by `r`; the one below
            // that, those shifted past its top.
            mark(along(b, -q), shifted(bits, &zero, axis, r));
            mark(along(b, -q - 1), shifted(&zero, bits, axis, r));
        }
    }
    out
}
