//! The data `build.rs` generated, embedded in the image. Each blob is its own static so the
//! linker (`--gc-sections`) keeps only the blobs an image uses.

/// Bytes at a 4-byte-aligned address, as flash holds a blob (`Blob::parse` requires it).
#[repr(C, align(4))]
pub struct Aligned<B: ?Sized>(pub B);

macro_rules! aligned_out_dir_bytes {
    ($file:literal) => {{
        static BYTES: &Aligned<[u8]> =
            &Aligned(*include_bytes!(concat!(env!("OUT_DIR"), "/", $file)));
        &BYTES.0
    }};
}

/// Row A's synthetic blob (MLP 2 × 128, 17 inputs).
pub static BLOB_A: &[u8] = aligned_out_dir_bytes!("blob_A.bin");
/// Row B's synthetic blob.
pub static BLOB_B: &[u8] = aligned_out_dir_bytes!("blob_B.bin");
/// Row C's synthetic blob.
pub static BLOB_C: &[u8] = aligned_out_dir_bytes!("blob_C.bin");
/// Row E's synthetic blob.
pub static BLOB_E: &[u8] = aligned_out_dir_bytes!("blob_E.bin");
/// Row F's synthetic blob.
pub static BLOB_F: &[u8] = aligned_out_dir_bytes!("blob_F.bin");
/// Row G's synthetic blob (2-layer LSTM 128 + MLP 256, 128, 128, 64).
pub static BLOB_G: &[u8] = aligned_out_dir_bytes!("blob_G.bin");

/// Row A's synthetic weights quantised to int8 (`synthetic::blob_i8`).
pub static BLOB_A_I8: &[u8] = aligned_out_dir_bytes!("blob_A_i8.bin");
/// Row G's synthetic weights quantised to int8: 320,288 payload bytes.
pub static BLOB_G_I8: &[u8] = aligned_out_dir_bytes!("blob_G_i8.bin");

/// The host's int8 outputs of rows A and G over their golden observations (golden layout,
/// see [`crate::golden`]), which the M4 must reproduce bit for bit.
pub static INT8: [(char, &[u8], &[u8]); 2] = [
    (
        'A',
        BLOB_A_I8,
        include_bytes!(concat!(env!("OUT_DIR"), "/int8_A.bin")),
    ),
    (
        'G',
        BLOB_G_I8,
        include_bytes!(concat!(env!("OUT_DIR"), "/int8_G.bin")),
    ),
];

/// Size of row A's blob, for a RAM copy.
pub const BLOB_A_LEN: usize = include_bytes!(concat!(env!("OUT_DIR"), "/blob_A.bin")).len();

/// Golden vectors of rows A, B, C, E, F, G (see [`crate::golden`]).
pub static GOLDEN: [(char, &[u8], &[u8]); 6] = [
    (
        'A',
        BLOB_A,
        include_bytes!(concat!(env!("OUT_DIR"), "/golden_A.bin")),
    ),
    (
        'B',
        BLOB_B,
        include_bytes!(concat!(env!("OUT_DIR"), "/golden_B.bin")),
    ),
    (
        'C',
        BLOB_C,
        include_bytes!(concat!(env!("OUT_DIR"), "/golden_C.bin")),
    ),
    (
        'E',
        BLOB_E,
        include_bytes!(concat!(env!("OUT_DIR"), "/golden_E.bin")),
    ),
    (
        'F',
        BLOB_F,
        include_bytes!(concat!(env!("OUT_DIR"), "/golden_F.bin")),
    ),
    (
        'G',
        BLOB_G,
        include_bytes!(concat!(env!("OUT_DIR"), "/golden_G.bin")),
    ),
];

/// The 30 values the host's firmware-core computed for `fixtures::observation_case()`
/// (f32 little-endian).
pub static OBSERVATION_EXPECTED: &[u8] =
    include_bytes!(concat!(env!("OUT_DIR"), "/observation_expected.bin"));

/// `size_of::<Controller>()` on this target, readable from the ELF by `tools size-report`
/// (symbol `OVERTAKE_CONTROLLER_BYTES`; kept in the image by [`crate::size_image::run`]).
#[unsafe(no_mangle)]
pub static OVERTAKE_CONTROLLER_BYTES: u32 =
    core::mem::size_of::<firmware_core::Controller<'static>>() as u32;

/// Stack one row-A step uses, as modelled (`controller::STEP_STACK_A_BYTES`), on this
/// target (symbol `OVERTAKE_SCRATCH_A_BYTES`).
#[unsafe(no_mangle)]
pub static OVERTAKE_SCRATCH_A_BYTES: u32 = firmware_core::controller::STEP_STACK_A_BYTES as u32;

/// Stack one row-G step uses, as modelled (`controller::STEP_STACK_G_BYTES`), on this
/// target (symbol `OVERTAKE_SCRATCH_G_BYTES`).
#[unsafe(no_mangle)]
pub static OVERTAKE_SCRATCH_G_BYTES: u32 = firmware_core::controller::STEP_STACK_G_BYTES as u32;

/// One shipped policy of the STM32F405 image (`tools/stm32f405-fit/policy_source.rs`), in
/// int8, with the host controller's rotor commands over `fixtures::flight` (the opponent
/// given when the blob's observation has one).
pub struct Shipped {
    /// Its slot, as a test name writes it: "stage1", "stage2".
    pub slot: &'static str,
    /// What it is (role, path, row).
    pub what: &'static str,
    /// The int8 blob.
    pub blob: &'static [u8],
    /// The host's commands: 4 f32 rpm per flight step, little-endian.
    pub commands: &'static [u8],
}

/// The stage-1 (row A) and the stage-2 (row G) policies the STM32F405 image holds.
pub static SHIPPED: [Shipped; 2] = [
    Shipped {
        slot: "stage1",
        what: include_str!(concat!(env!("OUT_DIR"), "/shipped_1.txt")),
        blob: aligned_out_dir_bytes!("shipped_1.bin"),
        commands: include_bytes!(concat!(env!("OUT_DIR"), "/shipped_1_commands.bin")),
    },
    Shipped {
        slot: "stage2",
        what: include_str!(concat!(env!("OUT_DIR"), "/shipped_2.txt")),
        blob: aligned_out_dir_bytes!("shipped_2.bin"),
        commands: include_bytes!(concat!(env!("OUT_DIR"), "/shipped_2_commands.bin")),
    },
];
