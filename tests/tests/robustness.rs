//! Bad files and bad inputs. Every row of docs/ROBUSTNESS.md names one of these
//! tests. Each engine call below runs inside `no_alloc`, a counting global allocator that
//! fails the test if the call allocates, so every error row is also shown to allocate
//! nothing (the corrupt files, arenas and inputs are prepared outside the counted region,
//! as firmware would have them in flash and statics).
//!
//! The files are the tiny test model's (ModelConfig::TINY, seeded synthetic weights),
//! altered byte by byte. Files that must get past the checksum to reach a deeper check are
//! re-checksummed with `scdp_engine::format::checksum` (docs/FORMAT.md, bytes 24..32).

#[allow(dead_code)]
#[path = "../../fuzz/src/alloc_guard.rs"]
mod alloc_guard;

use std::sync::OnceLock;

use alloc_guard::no_alloc;
use scdp_engine::format::{self, CHECKSUM_RANGE, DType, WeightsFile};
use scdp_engine::{
    ArenaPlan, Backend, Camera, ConfigError, Error, Model, ModelConfig, Noise, Observer, Policy,
    Prefix,
};
use scdp_tests::{available_backends, synthetic_weights_file, synthetic_weights_file_as};
use weights_tool::Quant;
use weights_tool::writer::{AlignedBytes, aligned_copy};

const CONFIG: ModelConfig = ModelConfig::TINY;
const TABLE: usize = 320;
const ENTRY: usize = 96;

// ---------------------------------------------------------------------------------------
// Files.

/// The valid weights file of the tiny model.
fn valid_file() -> &'static [u8] {
    static FILE: OnceLock<AlignedBytes> = OnceLock::new();
    FILE.get_or_init(|| synthetic_weights_file(&CONFIG, 3).unwrap())
        .as_slice()
}

fn u32_at(file: &[u8], at: usize) -> u32 {
    u32::from_le_bytes(file[at..at + 4].try_into().unwrap())
}

fn u64_at(file: &[u8], at: usize) -> u64 {
    u64::from_le_bytes(file[at..at + 8].try_into().unwrap())
}

fn set_u32(file: &mut [u8], at: usize, value: u32) {
    file[at..at + 4].copy_from_slice(&value.to_le_bytes());
}

fn set_u64(file: &mut [u8], at: usize, value: u64) {
    file[at..at + 8].copy_from_slice(&value.to_le_bytes());
}

fn fix_checksum(file: &mut [u8]) {
    let checksum = format::checksum(file);
    file[CHECKSUM_RANGE].copy_from_slice(&checksum.to_le_bytes());
}

fn tensor_count(file: &[u8]) -> usize {
    u32_at(file, 44) as usize
}

/// Byte offset of table row `index`.
fn entry(index: usize) -> usize {
    TABLE + index * ENTRY
}

/// The tiny model's weights file with int8 weights (docs/FORMAT.md, int8 entries).
fn int8_file() -> &'static [u8] {
    static FILE: OnceLock<AlignedBytes> = OnceLock::new();
    FILE.get_or_init(|| synthetic_weights_file_as(&CONFIG, 3, Quant::Int8).unwrap())
        .as_slice()
}

/// Index of the tensor called `name` in the valid file.
fn tensor_index(name: &str) -> usize {
    tensor_index_in(valid_file(), name)
}

/// Index of the tensor called `name` in `bytes`.
fn tensor_index_in(bytes: &[u8], name: &str) -> usize {
    let file = WeightsFile::parse(bytes).unwrap();
    (0..file.tensor_count())
        .find(|&index| file.entry(index).unwrap().name == name)
        .unwrap_or_else(|| panic!("no tensor {name}"))
}

/// A copy of the valid file with `edit` applied, checksum left as it was.
fn edited(edit: impl FnOnce(&mut Vec<u8>)) -> Vec<u8> {
    let mut file = valid_file().to_vec();
    edit(&mut file);
    file
}

/// A copy of the valid file with `edit` applied and the checksum recomputed, so that the
/// change reaches the checks behind the checksum.
fn rechecksummed(edit: impl FnOnce(&mut Vec<u8>)) -> Vec<u8> {
    let mut file = edited(edit);
    fix_checksum(&mut file);
    file
}

/// `Model::from_bytes` on a 64-byte aligned copy of `bytes`, checked to allocate nothing.
fn load(bytes: &[u8]) -> Result<(), Error> {
    let buffer = aligned_copy(bytes);
    no_alloc(|| Model::from_bytes(buffer.as_slice()).map(|_| ()))
}

/// Every tensor of a file, for rebuilding it with a different table.
struct Tensor {
    name: String,
    dtype: u32,
    dims: Vec<usize>,
    data: Vec<u8>,
}

fn tensors_of(bytes: &[u8]) -> Vec<Tensor> {
    let file = WeightsFile::parse(bytes).unwrap();
    (0..file.tensor_count())
        .map(|index| {
            let entry = file.entry(index).unwrap();
            Tensor {
                name: entry.name.to_string(),
                dtype: entry.dtype as u32,
                dims: entry.dims().to_vec(),
                data: file.data(&entry).to_vec(),
            }
        })
        .collect()
}

/// Lays `tensors` out as docs/FORMAT.md says, with the valid file's header and config.
fn rebuild(tensors: &[Tensor]) -> Vec<u8> {
    rebuild_onto(valid_file(), tensors)
}

/// [`rebuild`] with the header and config of `base`.
fn rebuild_onto(base: &[u8], tensors: &[Tensor]) -> Vec<u8> {
    let align = |n: usize| n.div_ceil(64) * 64;
    let mut file = base[..TABLE].to_vec();
    file.resize(align(TABLE + tensors.len() * ENTRY), 0);
    for (index, tensor) in tensors.iter().enumerate() {
        let at = entry(index);
        let offset = file.len();
        file[at..at + tensor.name.len()].copy_from_slice(tensor.name.as_bytes());
        set_u32(&mut file, at + 56, tensor.dtype);
        set_u32(&mut file, at + 60, tensor.dims.len() as u32);
        for (axis, &dim) in tensor.dims.iter().enumerate() {
            set_u32(&mut file, at + 64 + 4 * axis, dim as u32);
        }
        set_u64(&mut file, at + 80, offset as u64);
        set_u64(&mut file, at + 88, tensor.data.len() as u64);
        file.extend_from_slice(&tensor.data);
        file.resize(align(file.len()), 0);
    }
    set_u32(&mut file, 44, tensors.len() as u32);
    let len = file.len() as u64;
    set_u64(&mut file, 16, len);
    fix_checksum(&mut file);
    file
}

#[test]
fn the_unaltered_file_loads_and_the_allocation_counter_counts() {
    assert_eq!(load(valid_file()), Ok(()));
    let (_, count) = alloc_guard::allocations(|| std::hint::black_box(vec![1u8; 16]));
    assert!(count >= 1, "the counting allocator must see a Vec");
    // The rebuild helper reproduces the writer's layout exactly.
    assert_eq!(rebuild(&tensors_of(valid_file())), valid_file());
}

#[test]
fn weights_shorter_than_the_header_are_truncated() {
    for len in [0, 1, 8, 32, 63] {
        assert_eq!(
            load(&valid_file()[..len]),
            Err(Error::Truncated),
            "{len} bytes"
        );
    }
}

#[test]
fn weights_cut_short_are_truncated() {
    let len = valid_file().len();
    for cut in [64, 100, 320, 4096, len / 2, len - 64, len - 1] {
        assert_eq!(
            load(&valid_file()[..cut]),
            Err(Error::Truncated),
            "cut at {cut}"
        );
    }
}

/// A cut file whose header was made consistent again (length field and checksum fixed):
/// the reader must still notice that the config record, the table or a tensor is missing.
/// Before the fix in engine/src/format.rs, a file ending inside the config record (64 to
/// 319 bytes) panicked with an out-of-range slice (found by the `load_mutated` fuzzer).
#[test]
fn weights_cut_short_with_a_consistent_header_are_truncated() {
    let cut = |len: usize| {
        let mut file = valid_file()[..len].to_vec();
        set_u64(&mut file, 16, len as u64);
        fix_checksum(&mut file);
        file
    };
    for len in [64, 128, 192, 256, 320, 1024] {
        assert_eq!(load(&cut(len)), Err(Error::Truncated), "cut at {len}");
    }
    // The table is complete but the last tensor's data is not.
    let last = tensor_count(valid_file()) - 1;
    assert_eq!(
        load(&cut(valid_file().len() - 64)),
        Err(Error::BadTensorEntry { index: last })
    );
}

#[test]
fn weights_in_a_longer_buffer_are_bad_header() {
    for extra in [1, 8, 64, 4096] {
        let mut file = valid_file().to_vec();
        file.resize(file.len() + extra, 0);
        assert_eq!(load(&file), Err(Error::BadHeader), "{extra} trailing bytes");
    }
    // Padding the header counts (length field and checksum updated) is part of the file:
    // nothing requires the last tensor to end at the end of the file.
    let mut padded = valid_file().to_vec();
    padded.resize(padded.len() + 128, 0);
    let len = padded.len() as u64;
    set_u64(&mut padded, 16, len);
    fix_checksum(&mut padded);
    assert_eq!(load(&padded), Ok(()));
}

#[test]
fn zeroed_weights_are_bad_magic() {
    assert_eq!(load(&vec![0u8; valid_file().len()]), Err(Error::BadMagic));
    assert_eq!(load(&[0u8; 64]), Err(Error::BadMagic));
}

#[test]
fn wrong_magic_is_bad_magic() {
    for byte in 0..8 {
        let file = rechecksummed(|file| file[byte] ^= 0x20);
        assert_eq!(load(&file), Err(Error::BadMagic), "magic byte {byte}");
    }
}

#[test]
fn wrong_version_is_unsupported_version() {
    let current = scdp_engine::format::VERSION;
    for version in [0, current - 1, current + 1, u32::MAX] {
        let stale = edited(|file| set_u32(file, 8, version));
        let fixed = rechecksummed(|file| set_u32(file, 8, version));
        for file in [stale, fixed] {
            assert_eq!(
                load(&file),
                Err(Error::UnsupportedVersion {
                    found: version,
                    supported: current
                })
            );
        }
    }
}

#[test]
fn altered_bytes_are_checksum_mismatch() {
    let len = valid_file().len();
    // A reserved header byte, the config record, a table row, tensor data, the last byte,
    // the checksum itself.
    for at in [53, 64 + 7 * 4, entry(2) + 64, len / 2, len - 1, 24, 31] {
        let file = edited(|file| file[at] ^= 0x01);
        assert_eq!(
            load(&file),
            Err(Error::ChecksumMismatch),
            "byte {at} flipped"
        );
    }
    // Two flips that cancel in a byte-wise sum still change a word-wise FNV.
    let file = edited(|file| {
        file[1000] = file[1000].wrapping_add(1);
        file[1001] = file[1001].wrapping_sub(1);
    });
    assert_eq!(load(&file), Err(Error::ChecksumMismatch));
}

#[test]
fn misaligned_weights_buffer_is_misaligned_buffer() {
    let file = valid_file();
    let mut buffer = AlignedBytes::zeroed(file.len() + 64);
    for shift in [1, 4, 8, 16, 32, 63] {
        buffer.as_mut_slice()[shift..shift + file.len()].copy_from_slice(file);
        let slice = &buffer.as_slice()[shift..shift + file.len()];
        assert_eq!(
            no_alloc(|| Model::from_bytes(slice).map(|_| ())),
            Err(Error::MisalignedBuffer),
            "shifted by {shift}"
        );
    }
}

#[test]
fn inconsistent_header_fields_are_bad_header() {
    let len = valid_file().len() as u64;
    let cases: [(&str, usize, u64, usize); 12] = [
        ("header bytes 0", 12, 0, 4),
        ("header bytes 128", 12, 128, 4),
        ("file bytes shorter than the buffer", 16, len - 64, 8),
        ("config offset 0 (overlaps the header)", 32, 0, 4),
        ("config offset 128", 32, 128, 4),
        ("config bytes 255", 36, 255, 4),
        ("table offset 64 (overlaps the config)", 40, 64, 4),
        ("table offset 0 (overlaps the header)", 40, 0, 4),
        ("table offset beyond the file", 40, len + 64, 4),
        ("tensor count beyond the limit", 44, 100_001, 4),
        ("weight storage 2", 48, 2, 4),
        ("reserved bytes", 52, 1, 4),
    ];
    for (what, at, value, width) in cases {
        let file = rechecksummed(|file| match width {
            4 => set_u32(file, at, value as u32),
            _ => set_u64(file, at, value),
        });
        assert_eq!(load(&file), Err(Error::BadHeader), "{what}");
    }
    let file = rechecksummed(|file| file[63] = 1);
    assert_eq!(load(&file), Err(Error::BadHeader), "last reserved byte");
}

#[test]
fn tensor_table_beyond_the_file_is_truncated() {
    let file = rechecksummed(|file| set_u32(file, 44, 100_000));
    assert_eq!(load(&file), Err(Error::Truncated));
    let rows_that_fit = (valid_file().len() - TABLE) / ENTRY;
    let file = rechecksummed(|file| set_u32(file, 44, rows_that_fit as u32 + 1));
    assert_eq!(load(&file), Err(Error::Truncated));
}

#[test]
fn impossible_config_record_is_bad_config_record() {
    for (what, slot, value) in [
        ("imagenet_norm 2", 2, 2),
        ("backbone_norm 2", 3, 2),
        ("clip_sample 7", 27, 7),
        ("beta_schedule 1", 28, 1),
        ("prediction_type 1", 29, 1),
        ("4 U-Net levels", 30, 4),
        ("unused slot 31", 31, 1),
        ("unused slot 63", 63, 0xffff_ffff),
    ] {
        let file = rechecksummed(|file| set_u32(file, 64 + 4 * slot, value));
        assert_eq!(load(&file), Err(Error::BadConfigRecord), "{what}");
    }
}

#[test]
fn config_record_that_cannot_run_is_config_error() {
    for (slot, value, expected) in [
        (0, 0, ConfigError::ZeroImageSize),
        (1, 5000, ConfigError::ImageTooLarge),
        (7, 6, ConfigError::HorizonNotMultipleOfFour),
        (12, 5, ConfigError::StatePosIndex),
        (18, f32::NAN.to_bits(), ConfigError::PosScale),
        (18, f32::INFINITY.to_bits(), ConfigError::PosScale),
        (24, 0, ConfigError::Groups),
        (23, 4, ConfigError::KernelSize),
        (26, 0, ConfigError::InferenceSteps),
    ] {
        let file = rechecksummed(|file| set_u32(file, 64 + 4 * slot, value));
        assert_eq!(
            load(&file),
            Err(Error::Config(expected)),
            "slot {slot} = {value}"
        );
    }
}

/// `n_obs_steps - 1 + n_action_steps` overflowed u32 inside `ModelConfig::validate` for
/// `n_action_steps` near `u32::MAX`: a panic in builds with overflow checks, and in release
/// builds a wrapped sum that accepted the config (found by the `load_mutated` fuzzer).
#[test]
fn config_record_with_overflowing_step_counts_is_config_error() {
    for (slot, value, expected) in [
        (8, u32::MAX, ConfigError::ActionStepsBeyondHorizon),
        (8, u32::MAX - 1, ConfigError::ActionStepsBeyondHorizon),
        (8, u32::MAX - 6, ConfigError::ActionStepsBeyondHorizon),
        (9, u32::MAX, ConfigError::ReconstructionHorizon),
        (6, u32::MAX, ConfigError::ObsSteps),
    ] {
        let file = rechecksummed(|file| set_u32(file, 64 + 4 * slot, value));
        assert_eq!(
            load(&file),
            Err(Error::Config(expected)),
            "slot {slot} = {value}"
        );
    }
    let config = ModelConfig {
        n_action_steps: u32::MAX,
        ..CONFIG
    };
    assert_eq!(
        std::hint::black_box(config).validate(),
        Err(ConfigError::ActionStepsBeyondHorizon)
    );
}

#[test]
fn config_record_for_other_shapes_is_unexpected_tensor() {
    // Valid configs whose tensors differ from the file's: the first mismatch is reported.
    let feature_dim = tensor_index("proj.0.weight");
    for (slot, value, index) in [(4, 16, 0), (5, 16, feature_dim)] {
        let file = rechecksummed(|file| set_u32(file, 64 + 4 * slot, value));
        assert_eq!(
            load(&file),
            Err(Error::UnexpectedTensor { index }),
            "slot {slot}"
        );
    }
}

#[test]
fn tensor_entries_outside_the_file_or_overlapping_are_bad_tensor_entry() {
    let len = valid_file().len() as u64;
    let count = tensor_count(valid_file());
    let last = count - 1;
    let offset_of = |index: usize| u64_at(valid_file(), entry(index) + 80);
    type Edit = Box<dyn Fn(&mut Vec<u8>)>;
    fn case(
        what: &'static str,
        index: usize,
        edit: impl Fn(&mut Vec<u8>) + 'static,
    ) -> (&'static str, usize, Edit) {
        (what, index, Box::new(edit))
    }
    let ddim_steps = CONFIG.num_inference_steps;
    let cases = [
        case("offset at the end of the file", last, move |f| {
            set_u64(f, entry(last) + 80, len)
        }),
        case("offset beyond the file", 5, move |f| {
            set_u64(f, entry(5) + 80, len + 6400)
        }),
        case("offset beyond 32-bit usize", 5, |f| {
            set_u64(f, entry(5) + 80, 1 << 32)
        }),
        case("offset + length overflows", 5, |f| {
            set_u64(f, entry(5) + 80, u64::MAX - 63)
        }),
        case("offset into the header", 0, |f| {
            set_u64(f, entry(0) + 80, 0)
        }),
        case("offset into the table", 0, |f| {
            set_u64(f, entry(0) + 80, TABLE as u64)
        }),
        case("overlaps the previous tensor", 1, move |f| {
            set_u64(f, entry(1) + 80, offset_of(0))
        }),
        case("before the previous tensor", 7, move |f| {
            set_u64(f, entry(7) + 80, offset_of(3))
        }),
        case("misaligned offset", 4, move |f| {
            set_u64(f, entry(4) + 80, offset_of(4) + 4)
        }),
        case("data beyond the end of the file", last, move |f| {
            // scheduler.ddim [steps, 4] claims 1000 x more rows, consistently.
            set_u32(f, entry(last) + 64, ddim_steps * 1000);
            set_u64(f, entry(last) + 88, ddim_steps as u64 * 1000 * 16);
        }),
        case("length not dims x 4", 2, |f| f[entry(2) + 88] ^= 4),
        case("rank 0", 3, |f| set_u32(f, entry(3) + 60, 0)),
        case("rank 5", 3, |f| set_u32(f, entry(3) + 60, 5)),
        case("unused dim not 0", 3, |f| set_u32(f, entry(3) + 76, 1)),
        case("dims overflow", 3, |f| {
            set_u32(f, entry(3) + 60, 4);
            for axis in 0..4 {
                set_u32(f, entry(3) + 64 + 4 * axis, u32::MAX);
            }
        }),
        case("dtype 2", 6, |f| set_u32(f, entry(6) + 56, 2)),
        case("name not UTF-8", 6, |f| f[entry(6)] = 0xff),
        case("bytes after the name's NUL", 6, |f| f[entry(6) + 55] = b'x'),
    ];
    for (what, index, edit) in cases {
        let file = rechecksummed(|file| edit(file));
        assert_eq!(load(&file), Err(Error::BadTensorEntry { index }), "{what}");
    }
}

#[test]
fn tensor_other_than_the_expected_one_is_unexpected_tensor() {
    let scale = tensor_index("normalizer.action.scale");
    let renamed = rechecksummed(|file| file[entry(9)] ^= 0x01);
    assert_eq!(load(&renamed), Err(Error::UnexpectedTensor { index: 9 }));
    // backbone.conv1.weight [7, 7, 3, 8] stored as [7, 7, 8, 3]: same length, other shape.
    let permuted = rechecksummed(|file| {
        set_u32(file, entry(0) + 72, 8);
        set_u32(file, entry(0) + 76, 3);
    });
    assert_eq!(load(&permuted), Err(Error::UnexpectedTensor { index: 0 }));
    // An f32 tensor stored as i8 (length adjusted so the entry itself is consistent).
    let int8 = rechecksummed(|file| {
        set_u32(file, entry(scale) + 56, 1);
        set_u64(file, entry(scale) + 88, CONFIG.action_dim as u64);
    });
    assert_eq!(load(&int8), Err(Error::UnexpectedTensor { index: scale }));
    // Two tensors of the same shape swapped (action scale and offset): names are checked.
    let mut tensors = tensors_of(valid_file());
    tensors.swap(scale, scale + 1);
    assert_eq!(
        load(&rebuild(&tensors)),
        Err(Error::UnexpectedTensor { index: scale })
    );
}

#[test]
fn missing_and_extra_tensors() {
    let count = tensor_count(valid_file());
    let fewer = rechecksummed(|file| set_u32(file, 44, count as u32 - 1));
    assert_eq!(load(&fewer), Err(Error::MissingTensor { index: count - 1 }));
    let mut tensors = tensors_of(valid_file());
    tensors.truncate(10);
    assert_eq!(
        load(&rebuild(&tensors)),
        Err(Error::MissingTensor { index: 10 })
    );
    let mut tensors = tensors_of(valid_file());
    tensors.push(Tensor {
        name: "extra".into(),
        dtype: 0,
        dims: vec![4],
        data: vec![0; 16],
    });
    assert_eq!(load(&rebuild(&tensors)), Err(Error::ExtraTensors));
}

// ---------------------------------------------------------------------------------------
// Model, arena.

#[test]
fn weights_for_another_config_are_config_mismatch() {
    let model = Model::from_bytes(valid_file()).unwrap();
    assert_eq!(no_alloc(|| model.expect_config(&CONFIG)), Ok(()));
    let other_steps = ModelConfig {
        n_action_steps: 2,
        ..CONFIG
    };
    for planned in [ModelConfig::METAWORLD, ModelConfig::PANDA, other_steps] {
        assert_eq!(
            no_alloc(|| model.expect_config(&planned)),
            Err(Error::ConfigMismatch)
        );
    }
    // A file whose config differs from the planned one only in a field that does not
    // change any tensor still loads, and expect_config is what catches it.
    let file = rechecksummed(|file| set_u32(file, 64 + 8 * 4, 2));
    let buffer = aligned_copy(&file);
    let model = Model::from_bytes(buffer.as_slice()).unwrap();
    assert_eq!(
        no_alloc(|| model.expect_config(&CONFIG)),
        Err(Error::ConfigMismatch)
    );
    assert_eq!(no_alloc(|| model.expect_config(&other_steps)), Ok(()));
}

#[test]
fn arena_too_small_is_arena_too_small() {
    let model = Model::from_bytes(valid_file()).unwrap();
    let needed = ArenaPlan::new(&CONFIG).arena_bytes;
    let mut arena = AlignedBytes::zeroed(needed + 64);
    for found in [0, 64, needed / 2, needed - 64, needed - 1] {
        let result = no_alloc(|| Policy::new(&model, &mut arena.as_mut_slice()[..found]).err());
        assert_eq!(result, Some(Error::ArenaTooSmall { needed, found }));
    }
    for len in [needed, needed + 64] {
        let result = no_alloc(|| Policy::new(&model, &mut arena.as_mut_slice()[..len]).err());
        assert_eq!(result, None, "an arena of {len} bytes is enough");
    }
}

#[test]
fn misaligned_arena_is_misaligned_arena() {
    let model = Model::from_bytes(valid_file()).unwrap();
    let needed = ArenaPlan::new(&CONFIG).arena_bytes;
    let mut arena = AlignedBytes::zeroed(needed + 64);
    for shift in [1, 2, 4, 8, 16, 32, 60] {
        let slice = &mut arena.as_mut_slice()[shift..shift + needed];
        let result = no_alloc(|| Policy::new(&model, slice).err());
        assert_eq!(result, Some(Error::MisalignedArena), "shifted by {shift}");
    }
}

// ---------------------------------------------------------------------------------------
// Inputs.

fn frame_bytes() -> usize {
    (CONFIG.image_height * CONFIG.image_width * 3) as usize
}

fn image(phase: usize) -> Vec<u8> {
    (0..frame_bytes())
        .map(|i| ((i * 31 + phase * 17) % 256) as u8)
        .collect()
}

const STATE: [f32; 5] = [0.1, -0.05, 0.0, 0.3, -0.2];

const K: [[f32; 3]; 3] = [[40.0, 0.0, 23.5], [0.0, 40.0, 15.5], [0.0, 0.0, 1.0]];

fn extrinsics(translation: [f32; 3]) -> [[f32; 4]; 4] {
    [
        [1.0, 0.0, 0.0, translation[0]],
        [0.0, 1.0, 0.0, translation[1]],
        [0.0, 0.0, 1.0, translation[2]],
        [0.0, 0.0, 0.0, 1.0],
    ]
}

/// The base frame 0.6 m in front of the camera: every anchor lands in the image.
fn good_camera() -> Camera {
    Camera::new(&K, &extrinsics([0.0, 0.0, 0.6])).unwrap()
}

/// Runs `work` on a fresh policy of the tiny model (own arena), camera set, two frames
/// pushed.
fn with_policy<T>(work: impl FnOnce(&mut Policy<'_, '_>) -> T) -> T {
    let model = Model::from_bytes(valid_file()).unwrap();
    let mut arena = AlignedBytes::zeroed(ArenaPlan::new(&CONFIG).arena_bytes);
    let (first, second) = (image(0), image(1));
    let mut policy = Policy::new(&model, arena.as_mut_slice()).unwrap();
    no_alloc(|| {
        policy.set_camera(good_camera());
        policy.push_observation(&first, &STATE).unwrap();
        policy.push_observation(&second, &STATE).unwrap();
    });
    work(&mut policy)
}

/// Bits of `action_pred` of a seeded inference, or the error.
fn infer_bits(policy: &mut Policy<'_, '_>, noise: Noise<'_>) -> Result<Vec<u32>, Error> {
    let actions = no_alloc(|| policy.infer(noise))?;
    assert!(actions.action_pred().iter().all(|v| v.is_finite()));
    Ok(actions.action_pred().iter().map(|v| v.to_bits()).collect())
}

#[test]
fn wrong_image_size_or_frame_count_is_image_size() {
    let expected = frame_bytes();
    let two_frames = [image(2), image(3)].concat();
    let rgba = vec![0u8; expected / 3 * 4];
    with_policy(|policy| {
        let before = infer_bits(policy, Noise::Seed(1)).unwrap();
        for bad in [
            &[][..],
            &image(2)[..expected - 1],
            &[image(2), vec![0]].concat()[..],
            &two_frames[..],
            &rgba[..],
        ] {
            assert_eq!(
                no_alloc(|| policy.push_observation(bad, &STATE)),
                Err(Error::ImageSize {
                    expected,
                    found: bad.len()
                })
            );
        }
        // The rejected frames left the history as it was.
        assert_eq!(infer_bits(policy, Noise::Seed(1)).unwrap(), before);
    });
}

/// The run files of docs/SPEC.md section 8 hold `[To, H, W, 3]` images: a file with another frame
/// count is refused when it is read (weights-tool, std side), before the engine sees it.
#[test]
fn run_file_with_wrong_frame_count_is_refused() {
    use safetensors::{Dtype, tensor::TensorView};
    let dir = std::env::temp_dir().join(format!("scdp-robustness-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let (h, w) = (CONFIG.image_height as usize, CONFIG.image_width as usize);
    let f32_bytes =
        |values: &[f32]| -> Vec<u8> { values.iter().flat_map(|v| v.to_le_bytes()).collect() };
    let state = f32_bytes(&[STATE, STATE].concat());
    let k = f32_bytes(&K.concat());
    let t = f32_bytes(&extrinsics([0.0, 0.0, 0.6]).concat());
    for frames in [1usize, 2, 3] {
        let images = vec![7u8; frames * h * w * 3];
        let tensors = [
            (
                "images",
                TensorView::new(Dtype::U8, vec![frames, h, w, 3], &images).unwrap(),
            ),
            (
                "state",
                TensorView::new(Dtype::F32, vec![2, 5], &state).unwrap(),
            ),
            (
                "camera_k",
                TensorView::new(Dtype::F32, vec![3, 3], &k).unwrap(),
            ),
            (
                "camera_t",
                TensorView::new(Dtype::F32, vec![4, 4], &t).unwrap(),
            ),
        ];
        let path = dir.join(format!("frames{frames}.safetensors"));
        safetensors::serialize_to_file(tensors, None, &path).unwrap();
        let loaded = weights_tool::run::RunInputs::load(&path, &CONFIG);
        if frames == CONFIG.n_obs_steps as usize {
            assert!(loaded.is_ok(), "{:?}", loaded.err());
        } else {
            let message = loaded.err().unwrap().to_string();
            assert!(message.contains("`images`"), "{frames} frames: {message}");
        }
    }
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn wrong_state_length_is_state_size() {
    let frame = image(0);
    with_policy(|policy| {
        for len in [0, 4, 6, 10] {
            let state = vec![0.0f32; len];
            assert_eq!(
                no_alloc(|| policy.push_observation(&frame, &state)),
                Err(Error::StateSize {
                    expected: 5,
                    found: len
                })
            );
        }
    });
}

#[test]
fn non_finite_state_is_non_finite_state() {
    let frame = image(5);
    with_policy(|policy| {
        let before = infer_bits(policy, Noise::Seed(4)).unwrap();
        for index in 0..STATE.len() {
            for bad in [f32::NAN, f32::INFINITY, f32::NEG_INFINITY] {
                let mut state = STATE;
                state[index] = bad;
                assert_eq!(
                    no_alloc(|| policy.push_observation(&frame, &state)),
                    Err(Error::NonFiniteState)
                );
            }
        }
        assert_eq!(infer_bits(policy, Noise::Seed(4)).unwrap(), before);
    });
}

#[test]
fn wrong_noise_length_is_noise_size() {
    let expected = (CONFIG.horizon * CONFIG.action_dim) as usize;
    with_policy(|policy| {
        for len in [0, 1, expected - 1, expected + 1, 2 * expected] {
            let noise = vec![0.0f32; len];
            assert_eq!(
                infer_bits(policy, Noise::Given(&noise)),
                Err(Error::NoiseSize {
                    expected,
                    found: len
                })
            );
        }
    });
}

#[test]
fn non_finite_noise_is_non_finite_noise() {
    let len = (CONFIG.horizon * CONFIG.action_dim) as usize;
    with_policy(|policy| {
        for index in [0, 7, len - 1] {
            for bad in [f32::NAN, f32::INFINITY, f32::NEG_INFINITY] {
                let mut noise = vec![0.5f32; len];
                noise[index] = bad;
                assert_eq!(
                    infer_bits(policy, Noise::Given(&noise)),
                    Err(Error::NonFiniteNoise)
                );
            }
        }
    });
}

#[test]
fn non_finite_camera_is_rejected() {
    let t = extrinsics([0.0, 0.0, 0.6]);
    for bad in [f32::NAN, f32::INFINITY, f32::NEG_INFINITY] {
        for index in 0..9 {
            let mut k = K;
            k[index / 3][index % 3] = bad;
            assert_eq!(
                no_alloc(|| Camera::new(&k, &t)),
                Err(Error::BadIntrinsics),
                "K[{index}] = {bad}"
            );
        }
        for index in 0..16 {
            let mut t = t;
            t[index / 4][index % 4] = bad;
            assert_eq!(
                no_alloc(|| Camera::new(&K, &t)),
                Err(Error::BadExtrinsics),
                "T[{index}] = {bad}"
            );
        }
    }
}

#[test]
fn degenerate_intrinsics_are_bad_intrinsics() {
    let t = extrinsics([0.0, 0.0, 0.6]);
    let with = |row: usize, column: usize, value: f32| {
        let mut k = K;
        k[row][column] = value;
        k
    };
    for k in [
        with(0, 0, 0.0),
        with(0, 0, -0.0),
        with(1, 1, 0.0),
        with(0, 0, -40.0),
        with(1, 1, -1e-30),
        with(0, 1, 0.5),
        with(1, 0, 1.0),
        with(2, 0, 1.0),
        with(2, 2, 2.0),
        with(2, 2, 0.0),
    ] {
        assert_eq!(
            no_alloc(|| Camera::new(&k, &t)),
            Err(Error::BadIntrinsics),
            "{k:?}"
        );
    }
    // Positive control: tiny and huge but valid focal lengths, any finite centre.
    for k in [with(0, 0, 1e-20), with(1, 1, 1e20), with(0, 2, -1e6)] {
        assert!(no_alloc(|| Camera::new(&k, &t)).is_ok(), "{k:?}");
    }
}

/// Row-major rotation about a unit axis, through a unit quaternion in f32 (what a real
/// calibration's round-off looks like).
fn rotation_about(axis: [f32; 3], angle: f32) -> [[f32; 3]; 3] {
    let (s, w) = (angle / 2.0).sin_cos();
    let [x, y, z] = axis.map(|v| v * s);
    [
        [
            1.0 - 2.0 * (y * y + z * z),
            2.0 * (x * y - w * z),
            2.0 * (x * z + w * y),
        ],
        [
            2.0 * (x * y + w * z),
            1.0 - 2.0 * (x * x + z * z),
            2.0 * (y * z - w * x),
        ],
        [
            2.0 * (x * z - w * y),
            2.0 * (y * z + w * x),
            1.0 - 2.0 * (x * x + y * y),
        ],
    ]
}

fn transform(r: [[f32; 3]; 3], t: [f32; 3]) -> [[f32; 4]; 4] {
    let mut out = extrinsics(t);
    for row in 0..3 {
        out[row][..3].copy_from_slice(&r[row]);
    }
    out
}

#[test]
fn extrinsics_that_are_not_rigid_are_bad_extrinsics() {
    let axis = {
        let n = (1.0f32 + 4.0 + 9.0).sqrt();
        [1.0 / n, 2.0 / n, 3.0 / n]
    };
    let r = rotation_about(axis, 0.7);
    let scaled = |factor: f32| r.map(|row| row.map(|v| v * factor));
    let mut sheared = r;
    sheared[0][1] += 0.1;
    let mut reflected = r;
    reflected[2] = reflected[2].map(|v| -v);
    let mut bottom = transform(r, [0.1, 0.2, 0.6]);
    bottom[3] = [0.0, 0.0, 1.0, 1.0];
    let mut homogeneous_scale = transform(r, [0.1, 0.2, 0.6]);
    homogeneous_scale[3][3] = 2.0;
    let mut cases = vec![
        transform(scaled(2.0), [0.0; 3]),
        transform(scaled(1.01), [0.0; 3]),
        transform(scaled(0.0), [0.0; 3]),
        transform(scaled(-1.0), [0.0; 3]),
        transform(sheared, [0.0; 3]),
        transform(reflected, [0.0; 3]),
        transform(scaled(1e20), [0.0; 3]),
        bottom,
        homogeneous_scale,
    ];
    cases.push(transform(scaled(f32::MAX), [0.0; 3]));
    for t in cases {
        assert_eq!(
            no_alloc(|| Camera::new(&K, &t)),
            Err(Error::BadExtrinsics),
            "{t:?}"
        );
    }
    // Positive control: real rotations with f32 round-off and any finite translation.
    for angle in [0.0, 0.3, 1.0, 3.0, -2.5] {
        let t = transform(rotation_about(axis, angle), [1e6, -3.0, 0.25]);
        assert!(no_alloc(|| Camera::new(&K, &t)).is_ok(), "{t:?}");
    }
}

/// Records, at every step, whether the context part of `g` was all zeros.
struct ContextProbe {
    zero_context: Vec<bool>,
}

impl Observer for ContextProbe {
    fn step(&mut self, _: usize, _: &[f32], g: &[f32], _: &[f32], _: &[f32]) {
        let context = CONFIG.context_dim();
        let stride = context + CONFIG.state_dim as usize;
        self.zero_context.push(
            g.chunks(stride)
                .all(|frame| frame[..context].iter().all(|&v| v == 0.0)),
        );
    }
}

/// Actions (bits), anchors and the probe's verdicts of a seeded inference with `camera`.
fn run_with_camera(camera: Camera) -> (Vec<u32>, Vec<f32>, Vec<bool>) {
    with_policy(|policy| {
        no_alloc(|| policy.set_camera(camera));
        // Room for every step, so that the observer does not allocate while counted.
        let mut probe = ContextProbe {
            zero_context: Vec::with_capacity(CONFIG.num_inference_steps as usize),
        };
        let actions = no_alloc(|| policy.infer_observed(Noise::Seed(11), Prefix::NONE, &mut probe))
            .expect("a defined result, not an error");
        assert!(actions.action_pred().iter().all(|v| v.is_finite()));
        let bits = actions.action_pred().iter().map(|v| v.to_bits()).collect();
        assert_eq!(
            probe.zero_context.len(),
            CONFIG.num_inference_steps as usize
        );
        (bits, actions.anchors_uv().to_vec(), probe.zero_context)
    })
}

#[test]
fn anchors_behind_the_camera_or_outside_the_image_give_zero_context_and_finite_actions() {
    // Positive control: the good camera sees the anchors, so the context is not zero.
    let (seen, anchors, zero_context) = run_with_camera(good_camera());
    assert!(zero_context.iter().all(|&zero| !zero));
    assert!(anchors.iter().all(|v| v.is_finite()));

    // Base frame 5 m behind the camera: every anchor is invalid (NaN).
    let behind = Camera::new(&K, &extrinsics([0.0, 0.0, -5.0])).unwrap();
    let (behind_actions, anchors, zero_context) = run_with_camera(behind);
    assert!(zero_context.iter().all(|&zero| zero));
    assert!(anchors.iter().all(|v| v.is_nan()));

    // Principal point far away: every anchor is finite but far outside the 48 x 32 image.
    let k = [[40.0, 0.0, 5000.0], [0.0, 40.0, -3000.0], [0.0, 0.0, 1.0]];
    let outside = Camera::new(&k, &extrinsics([0.0, 0.0, 0.6])).unwrap();
    let (outside_actions, anchors, zero_context) = run_with_camera(outside);
    assert!(zero_context.iter().all(|&zero| zero));
    assert!(anchors.iter().all(|v| v.is_finite() && v.abs() > 100.0));

    // Same g (zero context, same states), same noise: the same actions, bit for bit; and
    // they differ from the ones computed with a seen context.
    assert_eq!(behind_actions, outside_actions);
    assert_ne!(behind_actions, seen);
}

/// The tiny model with every tensor value multiplied by `factor`, re-checksummed.
fn scaled_weights(factor: f32) -> Vec<u8> {
    let file = WeightsFile::parse(valid_file()).unwrap();
    let mut out = valid_file().to_vec();
    for index in 0..file.tensor_count() {
        let entry = file.entry(index).unwrap();
        for at in (entry.offset..entry.offset + entry.byte_len).step_by(4) {
            let value = f32::from_le_bytes(out[at..at + 4].try_into().unwrap());
            out[at..at + 4].copy_from_slice(&(value * factor).to_le_bytes());
        }
    }
    fix_checksum(&mut out);
    out
}

/// One seeded inference of the weights file `bytes` on the usual inputs.
fn infer_file(bytes: &[u8], state: &[f32; 5]) -> Result<Vec<u32>, Error> {
    infer_file_on(bytes, state, Backend::Auto)
}

/// [`infer_file`] on a chosen kernel backend.
fn infer_file_on(bytes: &[u8], state: &[f32; 5], backend: Backend) -> Result<Vec<u32>, Error> {
    let buffer = aligned_copy(bytes);
    let model = no_alloc(|| Model::from_bytes(buffer.as_slice())).expect("the file loads");
    let mut arena = AlignedBytes::zeroed(ArenaPlan::new(&CONFIG).arena_bytes);
    let (first, second) = (image(0), image(1));
    let mut policy =
        no_alloc(|| Policy::with_backend(&model, arena.as_mut_slice(), backend)).unwrap();
    no_alloc(|| {
        policy.set_camera(good_camera());
        policy.push_observation(&first, state)?;
        policy.push_observation(&second, state)
    })?;
    infer_bits(&mut policy, Noise::Seed(9))
}

#[test]
fn non_finite_denoising_is_non_finite_result() {
    assert!(infer_file(valid_file(), &STATE).is_ok());
    // Huge (finite) weights: activations overflow in the first U-Net pass.
    for factor in [1e30, 1e37, -1e35] {
        assert_eq!(
            infer_file(&scaled_weights(factor), &STATE),
            Err(Error::NonFiniteResult { step: 0 }),
            "weights x {factor}"
        );
    }
    // A NaN in the step-1 DDIM coefficients: step 0 is fine, step 1 is not.
    let ddim = tensor_index("scheduler.ddim");
    let ddim_at = u64_at(valid_file(), entry(ddim) + 80) as usize;
    let nan_step_1 = rechecksummed(|file| {
        file[ddim_at + 16..ddim_at + 20].copy_from_slice(&f32::NAN.to_le_bytes())
    });
    assert_eq!(
        infer_file(&nan_step_1, &STATE),
        Err(Error::NonFiniteResult { step: 1 })
    );
    // A zero action scale: the loop survives (the anchors are invalid), unnormalizing the
    // result divides by zero; the error names the step after the last.
    let scale = tensor_index("normalizer.action.scale");
    let scale_at = u64_at(valid_file(), entry(scale) + 80) as usize;
    let zero_scale = rechecksummed(|file| file[scale_at..scale_at + 4].fill(0));
    assert_eq!(
        infer_file(&zero_scale, &STATE),
        Err(Error::NonFiniteResult {
            step: CONFIG.num_inference_steps as usize
        })
    );
}

#[test]
fn huge_finite_state_gives_finite_actions_or_non_finite_result() {
    for magnitude in [1e3f32, 1e10, 1e30, 3e38] {
        let state = [magnitude, -magnitude, magnitude, magnitude, -magnitude];
        match infer_file(valid_file(), &state) {
            Ok(_) | Err(Error::NonFiniteResult { .. }) => {}
            Err(other) => panic!("state {magnitude}: {other:?}"),
        }
    }
    // 3e38 overflows `state * scale + offset` (scale > 1 for the state's first entries):
    // an error, never NaN actions.
    let state = [3e38, -3e38, 3e38, 3e38, -3e38];
    assert!(matches!(
        infer_file(valid_file(), &state),
        Err(Error::NonFiniteResult { step: 0 })
    ));
}

#[test]
fn an_inference_error_leaves_the_policy_usable() {
    let model = Model::from_bytes(valid_file()).unwrap();
    let mut arena = AlignedBytes::zeroed(ArenaPlan::new(&CONFIG).arena_bytes);
    let huge = [3e38f32; 5];
    let (first, second) = (image(0), image(1));
    let mut policy = Policy::new(&model, arena.as_mut_slice()).unwrap();
    policy.set_camera(good_camera());
    no_alloc(|| policy.push_observation(&first, &huge)).unwrap();
    assert!(matches!(
        infer_bits(&mut policy, Noise::Seed(9)),
        Err(Error::NonFiniteResult { .. })
    ));
    no_alloc(|| {
        policy.reset();
        policy.push_observation(&first, &STATE).unwrap();
        policy.push_observation(&second, &STATE).unwrap();
    });
    let recovered = infer_bits(&mut policy, Noise::Seed(9)).unwrap();
    assert_eq!(Ok(recovered), infer_file(valid_file(), &STATE));
}

#[test]
fn infer_before_push_is_no_observation() {
    let frame = image(0);
    let model = Model::from_bytes(valid_file()).unwrap();
    let mut arena = AlignedBytes::zeroed(ArenaPlan::new(&CONFIG).arena_bytes);
    let mut policy = Policy::new(&model, arena.as_mut_slice()).unwrap();
    no_alloc(|| policy.set_camera(good_camera()));
    assert_eq!(
        infer_bits(&mut policy, Noise::Seed(1)),
        Err(Error::NoObservation)
    );
    // After a push it works; after a reset it is refused again.
    no_alloc(|| policy.push_observation(&frame, &STATE)).unwrap();
    assert!(infer_bits(&mut policy, Noise::Seed(1)).is_ok());
    no_alloc(|| policy.reset());
    assert_eq!(
        infer_bits(&mut policy, Noise::Seed(1)),
        Err(Error::NoObservation)
    );
    // Rejected pushes do not count as observations.
    let _ = no_alloc(|| policy.push_observation(&frame[1..], &STATE));
    let _ = no_alloc(|| policy.push_observation(&frame, &[f32::NAN; 5]));
    assert_eq!(
        infer_bits(&mut policy, Noise::Seed(1)),
        Err(Error::NoObservation)
    );
}

#[test]
fn infer_before_camera_is_no_camera() {
    let frame = image(0);
    let model = Model::from_bytes(valid_file()).unwrap();
    let mut arena = AlignedBytes::zeroed(ArenaPlan::new(&CONFIG).arena_bytes);
    let mut policy = Policy::new(&model, arena.as_mut_slice()).unwrap();
    // Neither camera nor observation: the camera is reported first.
    assert_eq!(
        infer_bits(&mut policy, Noise::Seed(1)),
        Err(Error::NoCamera)
    );
    no_alloc(|| policy.push_observation(&frame, &STATE)).unwrap();
    assert_eq!(
        infer_bits(&mut policy, Noise::Seed(1)),
        Err(Error::NoCamera)
    );
    // A rejected calibration sets nothing.
    assert!(Camera::new(&[[0.0; 3]; 3], &extrinsics([0.0; 3])).is_err());
    assert_eq!(
        infer_bits(&mut policy, Noise::Seed(1)),
        Err(Error::NoCamera)
    );
    no_alloc(|| policy.set_camera(good_camera()));
    assert!(infer_bits(&mut policy, Noise::Seed(1)).is_ok());
}

/// Image size is the one config field that changes no tensor, so a file can declare any
/// legal size: the smallest and oddest ones must still run (docs/SPEC.md's convolution arithmetic
/// keeps every map at least 1 x 1).
#[test]
fn legal_but_degenerate_image_sizes_run() {
    for (height, width) in [(1, 1), (1, 9), (2, 3), (5, 1), (33, 17)] {
        let file = rechecksummed(|file| {
            set_u32(file, 64, height);
            set_u32(file, 68, width);
        });
        let buffer = aligned_copy(&file);
        let model = no_alloc(|| Model::from_bytes(buffer.as_slice())).unwrap();
        let config = *model.config();
        let mut arena = AlignedBytes::zeroed(ArenaPlan::new(&config).arena_bytes);
        let frame = vec![200u8; (height * width * 3) as usize];
        let k = [[10.0, 0.0, 0.0], [0.0, 10.0, 0.0], [0.0, 0.0, 1.0]];
        let camera = Camera::new(&k, &extrinsics([0.0, 0.0, 0.6])).unwrap();
        let mut policy = no_alloc(|| Policy::new(&model, arena.as_mut_slice())).unwrap();
        no_alloc(|| {
            policy.set_camera(camera);
            policy.push_observation(&frame, &STATE)
        })
        .unwrap();
        let bits = infer_bits(&mut policy, Noise::Seed(2)).unwrap();
        assert_eq!(bits.len(), (CONFIG.horizon * CONFIG.action_dim) as usize);
    }
}

/// A legal-looking config whose arena does not fit in the address space must be refused
/// with an error, never a panic, and never by accepting a small arena. The plan is computed
/// in `u64` (engine/src/plan.rs): on 32-bit targets (most firmware) `validate` refuses the
/// config, so the tool cannot write such a file and the loader refuses one; on 64-bit
/// hosts the config is valid and `Policy::new` wants more than a 1 MiB arena. Both run:
/// `cargo test -p scdp-tests --test robustness --target i686-unknown-linux-gnu`.
#[test]
fn config_whose_arena_exceeds_the_address_space_is_refused() {
    let config = ModelConfig {
        image_height: 4096,
        image_width: 4096,
        n_obs_steps: 8,
        horizon: 12,
        feature_dim: 64,
        ..CONFIG
    };
    let plan = ArenaPlan::new(&config);
    if usize::BITS < 64 {
        assert_eq!(config.validate(), Err(ConfigError::ArenaTooLarge));
        assert_eq!(plan.arena_bytes, usize::MAX, "saturated, not wrapped");
        // A file that claims this config: the valid file with the record's sizes replaced
        // (the tensors no longer match, but the config is checked first).
        let file = rechecksummed(|file| {
            for (slot, value) in [(0, 4096), (1, 4096), (5, 64), (6, 8), (7, 12)] {
                set_u32(file, 64 + 4 * slot, value);
            }
        });
        assert_eq!(load(&file), Err(Error::Config(ConfigError::ArenaTooLarge)));
        return;
    }
    assert_eq!(config.validate(), Ok(()));
    assert!(plan.arena_bytes as u64 > u32::MAX as u64);
    let weights = synthetic_weights_file(&config, 1).unwrap();
    let mut arena = AlignedBytes::zeroed(1 << 20);
    let outcome = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
        let model = Model::from_bytes(weights.as_slice())?;
        Policy::new(&model, arena.as_mut_slice()).map(|_| ())
    }));
    match outcome {
        Ok(Err(Error::ArenaTooSmall { needed, found })) => {
            assert_eq!(found, 1 << 20);
            assert_eq!(needed, plan.arena_bytes);
        }
        Ok(other) => panic!("a 1 MiB arena for this config: {other:?}"),
        Err(_) => panic!("Policy::new panicked"),
    }
}

// ---------------------------------------------------------------------------------------
// Int8 weights and kernel backends.

/// `bytes` with the f32 values at data offset of tensor `index` replaced by `edit`,
/// re-checksummed.
fn with_tensor_values(bytes: &[u8], index: usize, edit: impl Fn(f32) -> f32) -> Vec<u8> {
    let aligned = aligned_copy(bytes);
    let file = WeightsFile::parse(aligned.as_slice()).unwrap();
    let entry = file.entry(index).unwrap();
    let mut out = bytes.to_vec();
    for at in (entry.offset..entry.offset + entry.byte_len).step_by(4) {
        let value = f32::from_le_bytes(out[at..at + 4].try_into().unwrap());
        out[at..at + 4].copy_from_slice(&edit(value).to_le_bytes());
    }
    fix_checksum(&mut out);
    out
}

#[test]
fn int8_weights_load_and_run_without_allocating() {
    assert_eq!(u32_at(int8_file(), 48), 1, "the header says int8");
    assert_eq!(load(int8_file()), Ok(()));
    for backend in available_backends() {
        let bits = infer_file_on(int8_file(), &STATE, backend).unwrap();
        assert_eq!(bits.len(), (CONFIG.horizon * CONFIG.action_dim) as usize);
    }
}

#[test]
fn int8_scale_that_is_zero_negative_or_not_finite_is_unexpected_tensor() {
    let scale = tensor_index_in(int8_file(), "backbone.layer1.0.conv1.weight_scale");
    let film = tensor_index_in(int8_file(), "unet.down.0.0.film.weight_scale");
    for index in [scale, film] {
        for bad in [0.0, -0.0, -1.0, f32::NAN, f32::INFINITY, f32::NEG_INFINITY] {
            let file = with_tensor_values(int8_file(), index, |_| bad);
            assert_eq!(
                load(&file),
                Err(Error::UnexpectedTensor { index }),
                "scale {bad}"
            );
        }
    }
}

#[test]
fn int8_weight_without_its_scale_is_unexpected_tensor() {
    let weight = tensor_index_in(int8_file(), "backbone.layer1.0.conv1.weight");
    let mut tensors = tensors_of(int8_file());
    assert_eq!(tensors[weight].dtype, 1, "stored as i8");
    tensors.remove(weight + 1);
    let mut file = rebuild_onto(int8_file(), &tensors);
    fix_checksum(&mut file);
    assert_eq!(
        load(&file),
        Err(Error::UnexpectedTensor { index: weight + 1 })
    );
    // An i8 tensor where the engine only reads f32 (a bias).
    let bias = weight + 2;
    assert!(tensors_of(int8_file())[bias].name.ends_with(".bias"));
    let mut tensors = tensors_of(int8_file());
    tensors[bias].dtype = 1;
    let len = tensors[bias].data.len() / 4;
    tensors[bias].data.truncate(len);
    assert_eq!(
        load(&rebuild_onto(int8_file(), &tensors)),
        Err(Error::UnexpectedTensor { index: bias })
    );
}

/// Huge but valid (finite, positive) scales: the int8 layers overflow, and the policy says
/// so instead of returning actions.
#[test]
fn int8_scales_that_overflow_are_non_finite_result() {
    let file = WeightsFile::parse(int8_file()).unwrap();
    let mut bytes = int8_file().to_vec();
    for index in 0..file.tensor_count() {
        if file.entry(index).unwrap().name.ends_with("_scale") {
            bytes = with_tensor_values(&bytes, index, |_| 3e38);
        }
    }
    for backend in available_backends() {
        assert!(
            matches!(
                infer_file_on(&bytes, &STATE, backend),
                Err(Error::NonFiniteResult { .. })
            ),
            "{backend:?}"
        );
    }
}

/// The header's storage field is checked against the tensors: a file whose weights are
/// all f32 but whose header says int8, and the reverse, are `BadHeader`.
#[test]
fn weight_storage_field_that_contradicts_the_tensors_is_bad_header() {
    let says_int8 = rechecksummed(|file| set_u32(file, 48, 1));
    assert_eq!(load(&says_int8), Err(Error::BadHeader));
    let mut says_f32 = int8_file().to_vec();
    set_u32(&mut says_f32, 48, 0);
    fix_checksum(&mut says_f32);
    assert_eq!(load(&says_f32), Err(Error::BadHeader));
}

#[test]
fn unavailable_backend_is_backend_unavailable() {
    let model = Model::from_bytes(valid_file()).unwrap();
    let mut arena = AlignedBytes::zeroed(ArenaPlan::new(&CONFIG).arena_bytes);
    let available = scdp_engine::kernels::select(Backend::Avx2).is_some();
    let result = no_alloc(|| {
        Policy::with_backend(&model, arena.as_mut_slice(), Backend::Avx2)
            .map(|policy| policy.kernels_name())
    });
    if available {
        assert_eq!(result, Ok("avx2"));
    } else {
        assert_eq!(result, Err(Error::BackendUnavailable));
    }
    for backend in [Backend::Auto, Backend::Scalar] {
        assert!(no_alloc(|| Policy::with_backend(&model, arena.as_mut_slice(), backend)).is_ok());
    }
}

/// The tiny config with a deepest U-Net level of 516 channels: the first block of the up
/// path reads the concatenation, 1032 channels, past the 1024 inputs up to which the int8
/// convolutions' exact i32 sums are guaranteed (`kernels::MAX_DIGIT_CHANNELS`).
const WIDE: ModelConfig = ModelConfig {
    down_dims: [16, 32, 516],
    ..ModelConfig::TINY
};

/// The tool keeps convolutions wider than that in f32 in an int8 file, and the file runs.
#[test]
fn int8_convolutions_too_wide_for_exact_sums_are_stored_in_f32_and_run() {
    let file = synthetic_weights_file_as(&WIDE, 5, Quant::Int8).unwrap();
    let tensors = tensors_of(file.as_slice());
    let dtype_of = |name: &str| tensors.iter().find(|t| t.name == name).unwrap().dtype;
    assert_eq!(dtype_of("unet.up.0.0.conv0.weight"), DType::F32 as u32);
    assert_eq!(dtype_of("unet.up.0.0.residual.weight"), DType::F32 as u32);
    assert_eq!(dtype_of("unet.up.0.0.conv1.weight"), DType::I8 as u32);
    let model = Model::from_bytes(file.as_slice()).unwrap();
    let mut arena = AlignedBytes::zeroed(ArenaPlan::new(&WIDE).arena_bytes);
    let mut policy = Policy::new(&model, arena.as_mut_slice()).unwrap();
    policy.set_camera(good_camera());
    let pixels = (WIDE.image_height * WIDE.image_width) as usize;
    let frame: Vec<u8> = (0..3 * pixels).map(|i| (i % 251) as u8).collect();
    policy
        .push_observation(&frame, &vec![0.1; WIDE.state_dim as usize])
        .unwrap();
    let noise = vec![0.5; (WIDE.horizon * WIDE.action_dim) as usize];
    let actions = policy.infer(Noise::Given(&noise)).unwrap();
    assert!(actions.action_pred().iter().all(|a| a.is_finite()));
}

/// A file that stores such a convolution as int8 anyway (another tool, or an edit) is
/// refused at load with the tensor's index, instead of reaching a kernel that would panic.
#[test]
fn int8_convolution_too_wide_for_exact_sums_is_an_unexpected_tensor() {
    let file = synthetic_weights_file_as(&WIDE, 5, Quant::Int8).unwrap();
    let mut tensors = tensors_of(file.as_slice());
    let name = "unet.up.0.0.conv0.weight";
    let index = tensors.iter().position(|t| t.name == name).unwrap();
    let dims = tensors[index].dims.clone();
    let (taps, inputs, outputs) = (dims[0], dims[1], dims[2]);
    tensors[index].dtype = DType::I8 as u32;
    tensors[index].data = vec![1; taps * inputs.div_ceil(4) * 4 * outputs];
    let scale = Tensor {
        name: format!("{name}_scale"),
        dtype: DType::F32 as u32,
        dims: vec![outputs],
        data: 1.0f32.to_le_bytes().repeat(outputs),
    };
    tensors.insert(index + 1, scale);
    let edited = rebuild_onto(file.as_slice(), &tensors);
    assert_eq!(load(&edited), Err(Error::UnexpectedTensor { index }));
}

/// Narrow (8-bit) activation codes are a residual-block layer's: a file that asks for them
/// on a layer whose input can be negative (the U-Net) or that the engine quantizes once for
/// several readers at a frame's level (the projections) is refused at that tensor's index;
/// on a residual block's convolution it loads and runs.
#[test]
fn narrow_activation_codes_are_refused_where_the_engine_has_no_narrow_path() {
    let file = synthetic_weights_file_as(&ModelConfig::TINY, 5, Quant::Int8).unwrap();
    for name in [
        "proj.0.weight",
        "unet.down.0.downsample.weight",
        "unet.mid.0.film.weight",
    ] {
        let mut tensors = tensors_of(file.as_slice());
        let index = tensors.iter().position(|t| t.name == name).unwrap();
        assert_eq!(tensors[index].dtype, DType::I8 as u32, "{name}");
        tensors[index].dtype = DType::I8Narrow as u32;
        let edited = rebuild_onto(file.as_slice(), &tensors);
        assert_eq!(
            load(&edited),
            Err(Error::UnexpectedTensor { index }),
            "{name}"
        );
    }
    // The residual blocks' convolutions have one, in the trunk and in the U-Net.
    let mut tensors = tensors_of(file.as_slice());
    for name in [
        "backbone.layer2.0.conv1.weight",
        "unet.down.0.0.conv0.weight",
    ] {
        let index = tensors.iter().position(|t| t.name == name).unwrap();
        tensors[index].dtype = DType::I8Narrow as u32;
    }
    assert_tiny_file_runs(&rebuild_onto(file.as_slice(), &tensors));
}

/// Makes `tensors[index]` (an int8 weight followed by its scales) a refined one: a second
/// plane and its scales after the first's (here copies of them), the scale entry
/// `[2, channels]` unless `scale_dims` says otherwise.
fn refine(tensors: &mut [Tensor], index: usize, scale_dims: Option<Vec<usize>>) {
    tensors[index].dtype = DType::I8Refined as u32;
    tensors[index].data = tensors[index].data.repeat(2);
    let channels = tensors[index + 1].dims[0];
    tensors[index + 1].dims = scale_dims.unwrap_or(vec![2, channels]);
    tensors[index + 1].data = tensors[index + 1].data.repeat(2);
}

/// A second weight plane is a residual-block convolution's: a file that gives one to a
/// projection, a U-Net downsampling or a FiLM matrix is refused at that tensor's index, one
/// whose scale entry is not `[2, channels]` at the scale's; on a residual block's
/// convolution, in the trunk and in the U-Net, it loads and runs.
#[test]
fn refined_weights_are_refused_where_the_engine_has_no_second_plane() {
    let file = synthetic_weights_file_as(&ModelConfig::TINY, 5, Quant::Int8).unwrap();
    let index_of = |tensors: &[Tensor], name: &str| {
        let index = tensors.iter().position(|t| t.name == name).unwrap();
        assert_eq!(tensors[index].dtype, DType::I8 as u32, "{name}");
        index
    };
    for name in [
        "proj.0.weight",
        "unet.down.0.downsample.weight",
        "unet.mid.0.film.weight",
    ] {
        let mut tensors = tensors_of(file.as_slice());
        let index = index_of(&tensors, name);
        refine(&mut tensors, index, None);
        let edited = rebuild_onto(file.as_slice(), &tensors);
        let refused = Err(Error::UnexpectedTensor { index });
        assert_eq!(load(&edited), refused, "{name}");
    }
    let name = "backbone.layer2.0.conv1.weight";
    let mut tensors = tensors_of(file.as_slice());
    let index = index_of(&tensors, name);
    let channels = tensors[index + 1].dims[0];
    refine(&mut tensors, index, Some(vec![2 * channels]));
    let edited = rebuild_onto(file.as_slice(), &tensors);
    let refused = Err(Error::UnexpectedTensor { index: index + 1 });
    assert_eq!(load(&edited), refused, "{name} with flat scales");

    let mut tensors = tensors_of(file.as_slice());
    for name in [
        "backbone.layer2.0.conv1.weight",
        "unet.down.0.0.conv0.weight",
    ] {
        let index = index_of(&tensors, name);
        refine(&mut tensors, index, None);
    }
    assert_tiny_file_runs(&rebuild_onto(file.as_slice(), &tensors));
}

/// A TINY weights file loads, and one inference on a plain frame gives finite actions.
fn assert_tiny_file_runs(bytes: &[u8]) {
    let edited = aligned_copy(bytes);
    let model = Model::from_bytes(edited.as_slice()).unwrap();
    let config = ModelConfig::TINY;
    let mut arena = AlignedBytes::zeroed(ArenaPlan::new(&config).arena_bytes);
    let mut policy = Policy::new(&model, arena.as_mut_slice()).unwrap();
    policy.set_camera(good_camera());
    let pixels = (config.image_height * config.image_width) as usize;
    let frame: Vec<u8> = (0..3 * pixels).map(|i| (i % 251) as u8).collect();
    policy
        .push_observation(&frame, &vec![0.1; config.state_dim as usize])
        .unwrap();
    let noise = vec![0.5; (config.horizon * config.action_dim) as usize];
    let actions = policy.infer(Noise::Given(&noise)).unwrap();
    assert!(actions.action_pred().iter().all(|a| a.is_finite()));
}

/// The tiny model's int8 file with every residual-block layer on 8-bit codes, and the same
/// with the pair layout added as `weights-tool add-pairs` adds it.
fn narrow_and_paired_files() -> &'static (AlignedBytes, AlignedBytes) {
    static FILES: OnceLock<(AlignedBytes, AlignedBytes)> = OnceLock::new();
    FILES.get_or_init(|| {
        let narrow = scdp_tests::synthetic_narrow_weights_file(&CONFIG, 3).unwrap();
        let paired = weights_tool::writer::add_weight_pairs(narrow.as_slice()).unwrap();
        (narrow, aligned_copy(&paired))
    })
}

/// Indices of the pair-layout tensors of `bytes`.
fn pair_tensors(bytes: &[u8]) -> Vec<usize> {
    let file = WeightsFile::parse(bytes).unwrap();
    (0..file.tensor_count())
        .filter(|&index| file.entry(index).unwrap().dtype.is_pairs())
        .collect()
}

/// Every 8-bit convolution gets its pair layout right after its scales; the file loads
/// without allocating and every backend gives the bits it gives without them (on x86 the
/// backends read the quads; under qemu's `-cpu max`, `simd-bits` checks `i8mm`, which reads
/// the pairs, against these). Adding them twice changes nothing.
#[test]
fn a_file_with_the_pair_layout_loads_and_gives_the_same_bits() {
    let (narrow, paired) = narrow_and_paired_files();
    let (narrow, paired) = (narrow.as_slice(), paired.as_slice());
    let file = WeightsFile::parse(paired).unwrap();
    let pairs = pair_tensors(paired);
    let narrow_convolutions = (0..file.tensor_count())
        .map(|index| file.entry(index).unwrap())
        .filter(|entry| matches!(entry.dtype, DType::I8Narrow | DType::I8NarrowRefined))
        .filter(|entry| entry.rank >= 3)
        .count();
    assert!(
        narrow_convolutions > 0,
        "the narrow file has 8-bit convolutions"
    );
    assert_eq!(pairs.len(), narrow_convolutions);
    for &index in &pairs {
        let (weight, entry) = (file.entry(index - 2).unwrap(), file.entry(index).unwrap());
        assert_eq!(entry.name, format!("{}.pairs", weight.name));
        assert_eq!(entry.dims(), weight.dims());
    }
    assert_eq!(load(paired), Ok(()));
    for backend in available_backends() {
        assert_eq!(
            infer_file_on(paired, &STATE, backend),
            infer_file_on(narrow, &STATE, backend),
            "{backend:?}"
        );
    }
    let again = weights_tool::writer::add_weight_pairs(paired).unwrap();
    assert_eq!(again, paired, "pairs added twice");
}

/// A pair layout where the file has no 8-bit convolution before it, of another weight's
/// dims, with the wrong number of planes, or in a weight's place is an unexpected tensor;
/// one whose length is not its dims' is a bad entry.
#[test]
fn a_misplaced_or_misshapen_pair_layout_is_rejected() {
    let (_, paired) = narrow_and_paired_files();
    let paired = paired.as_slice();
    let first = pair_tensors(paired)[0];
    let tensors = || tensors_of(paired);
    let rebuilt = |tensors: &[Tensor]| rebuild_onto(paired, tensors);
    // Another layer's dims (the data resized to match them).
    let mut other = tensors();
    let later = *pair_tensors(paired)
        .iter()
        .find(|&&index| other[index].dims != other[first].dims)
        .expect("layers of two shapes");
    other[first].dims = other[later].dims.clone();
    other[first].data = other[later].data.clone();
    let unexpected = Err(Error::UnexpectedTensor { index: first });
    assert_eq!(load(&rebuilt(&other)), unexpected, "another layer's dims");
    // Two planes for a weight of one.
    let mut planes = tensors();
    assert_eq!(planes[first].dtype, DType::I8Pairs as u32);
    planes[first].dtype = DType::I8RefinedPairs as u32;
    let doubled = planes[first].data.repeat(2);
    planes[first].data = doubled;
    assert_eq!(load(&rebuilt(&planes)), unexpected, "two planes");
    // Before its weight: the weight's place holds something else.
    let mut moved = tensors();
    let pairs = moved.remove(first);
    moved.insert(first - 2, pairs);
    let misplaced = Err(Error::UnexpectedTensor { index: first - 2 });
    assert_eq!(load(&rebuilt(&moved)), misplaced, "in the weight's place");
    // After a layer on 15-bit codes, which no backend reads in pairs.
    let mut wide = tensors();
    wide[first - 2].dtype = DType::I8 as u32;
    assert_eq!(load(&rebuilt(&wide)), unexpected, "after a 15-bit layer");
    // Shorter than its dims say.
    let mut short = tensors();
    let len = short[first].data.len();
    short[first].data.truncate(len - 64);
    let bad = Err(Error::BadTensorEntry { index: first });
    assert_eq!(load(&rebuilt(&short)), bad, "short");
}
