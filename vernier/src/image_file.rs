//! Image files: reading and decoding PNG, JPEG, TIFF and PNM within resource limits, and
//! [`FrameReader`], which reads a stream of files into buffers kept from frame to frame.

use crate::error::{Error, Result};
use crate::grey_image::GreyImage;
use std::path::Path;

/// Resource limits of an image decode.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub struct DecodeLimits {
    /// Largest image accepted, pixels (`width × height`); default
    /// [`limits::DEFAULT_MAX_PIXELS`](crate::limits::DEFAULT_MAX_PIXELS) (100 MP). The
    /// decoder's allocation is bounded by 8 bytes per pixel of it.
    pub max_pixels: u64,
}

impl Default for DecodeLimits {
    fn default() -> Self {
        DecodeLimits {
            max_pixels: crate::limits::DEFAULT_MAX_PIXELS,
        }
    }
}

impl DecodeLimits {
    /// Limits of at most `max_pixels` pixels.
    pub fn with_max_pixels(max_pixels: u64) -> Self {
        DecodeLimits { max_pixels }
    }

    fn max_alloc(&self) -> u64 {
        self.max_pixels
            .saturating_mul(crate::limits::MAX_DECODED_BYTES_PER_PIXEL)
            .saturating_add(crate::limits::FILE_SIZE_SLACK)
    }
}

/// Reads and decodes an image file (format from its content, else its extension) within
/// `limits`: the file size, the header's dimensions (before any pixel is decoded, so a
/// decompression bomb costs nothing) and the decoder's allocations are bounded, and truncated
/// or corrupted files are rejected rather than decoded in part: a JPEG must end with its
/// end-of-image marker, a PNG must pass every chunk CRC and end with `IEND`.
pub fn decode_image_file(path: &Path, limits: &DecodeLimits) -> Result<image::DynamicImage> {
    let mut bytes = Vec::new();
    read_file_into(path, limits, &mut bytes)?;
    decode_image_bytes(&bytes, path, limits)
}

/// Reads the file at `path` into `bytes` (cleared first, its capacity kept) when its size is
/// within `limits`.
fn read_file_into(path: &Path, limits: &DecodeLimits, bytes: &mut Vec<u8>) -> Result<()> {
    let read_err = |reason: String| read_error(path, reason);
    let size = std::fs::metadata(path)
        .map_err(|e| read_err(e.to_string()))?
        .len();
    if size > limits.max_alloc() {
        return Err(read_err(format!(
            "the file is {size} bytes, more than any image within --max-pixels / \
             max_image_pixels {} could need",
            crate::limits::megapixels(limits.max_pixels)
        )));
    }
    // One byte more than the file: `read_to_end` then meets its end without growing.
    crate::frame_buffer::reserve_fresh(bytes, usize::try_from(size).unwrap_or(0).saturating_add(1));
    std::fs::File::open(path)
        .and_then(|mut file| std::io::Read::read_to_end(&mut file, bytes))
        .map_err(|e| read_err(e.to_string()))?;
    Ok(())
}

/// Decodes an in-memory image file within `limits` ([`decode_image_file`]'s checks).
pub(crate) fn decode_image_bytes(
    bytes: &[u8],
    path: &Path,
    limits: &DecodeLimits,
) -> Result<image::DynamicImage> {
    checked_reader(bytes, path, limits)?
        .decode()
        .map_err(|e| read_error(path, e))
}

/// An `Error::ImageRead` of the file at `path`.
fn read_error(path: &Path, reason: impl ToString) -> Error {
    Error::ImageRead {
        path: path.to_path_buf(),
        reason: reason.to_string(),
    }
}

/// A reader of an in-memory image file whose structure, header and size passed
/// [`decode_image_file`]'s checks, with the decoder's allocations bounded by `limits`.
fn checked_reader<'a>(
    bytes: &'a [u8],
    path: &Path,
    limits: &DecodeLimits,
) -> Result<image::ImageReader<std::io::Cursor<&'a [u8]>>> {
    let read_err = |reason: String| read_error(path, reason);
    let format = image::guess_format(bytes)
        .or_else(|_| image::ImageFormat::from_path(path))
        .map_err(|e| read_err(e.to_string()))?;
    check_integrity(bytes, format).map_err(read_err)?;
    let reader = |format| image::ImageReader::with_format(std::io::Cursor::new(bytes), format);
    let (w, h) = match png_dimensions(bytes) {
        // The PNG decoder refuses a huge header with a bare "Memory limit exceeded".
        Some(dims) if format == image::ImageFormat::Png => dims,
        _ => {
            let mut probe = reader(format);
            let mut probe_limits = image::Limits::default();
            probe_limits.max_alloc = Some(limits.max_alloc());
            probe.limits(probe_limits);
            probe.into_dimensions().map_err(|e| match e {
                image::ImageError::Limits(_) => read_err(format!(
                    "the image header asks for more memory than --max-pixels / \
                     max_image_pixels {} allows",
                    crate::limits::megapixels(limits.max_pixels)
                )),
                other => read_err(other.to_string()),
            })?
        }
    };
    crate::limits::check_image_pixels(w as u64, h as u64, limits.max_pixels)
        .map_err(|e| read_err(e.to_string().trim_start_matches("invalid image: ").into()))?;
    let mut reader = reader(format);
    let mut decode_limits = image::Limits::default();
    decode_limits.max_alloc = Some(limits.max_alloc());
    let side = u32::try_from(limits.max_pixels).unwrap_or(u32::MAX);
    decode_limits.max_image_width = Some(side);
    decode_limits.max_image_height = Some(side);
    reader.limits(decode_limits);
    Ok(reader)
}

/// Structural checks that decoders skip: a partial file must not decode as a partial image.
fn check_integrity(bytes: &[u8], format: image::ImageFormat) -> std::result::Result<(), String> {
    match format {
        image::ImageFormat::Jpeg => {
            let end = bytes.iter().rposition(|&b| b != 0).map_or(0, |i| i + 1);
            if end < 4 || bytes[end - 2..end] != [0xFF, 0xD9] {
                return Err(
                    "truncated JPEG: the file does not end with the end-of-image marker (FF D9)"
                        .into(),
                );
            }
            Ok(())
        }
        image::ImageFormat::Png => check_png_chunks(bytes),
        _ => Ok(()),
    }
}

/// Width and height of a PNG file's `IHDR` chunk (the first chunk).
fn png_dimensions(bytes: &[u8]) -> Option<(u32, u32)> {
    let ihdr = bytes.get(8..24)?;
    if &ihdr[4..8] != b"IHDR" {
        return None;
    }
    let be = |b: &[u8]| u32::from_be_bytes([b[0], b[1], b[2], b[3]]);
    Some((be(&ihdr[8..12]), be(&ihdr[12..16])))
}

/// Walks the chunks of a PNG file: every CRC must match and the last chunk must be `IEND`.
fn check_png_chunks(bytes: &[u8]) -> std::result::Result<(), String> {
    let mut at = 8usize;
    loop {
        let Some(header) = bytes.get(at..at + 8) else {
            return Err(format!(
                "truncated PNG: the file ends at byte {} without an IEND chunk",
                bytes.len()
            ));
        };
        let length = u32::from_be_bytes([header[0], header[1], header[2], header[3]]) as usize;
        let kind = &header[4..8];
        let name = String::from_utf8_lossy(kind).into_owned();
        let Some(end) = (at + 8)
            .checked_add(length)
            .filter(|&end| end.saturating_add(4) <= bytes.len())
        else {
            return Err(format!(
                "truncated PNG: chunk `{name}` at byte {at} ({length} bytes) runs past the end \
                 of the file"
            ));
        };
        let stored = &bytes[end..end + 4];
        let crc = crc32fast::hash(&bytes[at + 4..end]);
        if crc.to_be_bytes() != stored {
            return Err(format!(
                "corrupted PNG: chunk `{name}` at byte {at} fails its CRC"
            ));
        }
        if kind == b"IEND" {
            return Ok(());
        }
        at = end + 4;
    }
}

/// Reads a stream of image files into grey images, keeping its buffers from frame to frame:
/// the file's bytes, the decoded samples and the grey pixels are allocated (and their pages
/// mapped) once per size, not once per frame (on a 5 MP frame, ~30 MB of fresh pages cost
/// more than the conversion itself). The checks and limits are [`decode_image_file`]'s.
///
/// ```no_run
/// # fn main() -> vernier::Result<()> {
/// let mut reader = vernier::FrameReader::default();
/// let limits = vernier::DecodeLimits::default();
/// for path in ["frame_0.pgm", "frame_1.pgm"] {
///     let image = reader.read(path.as_ref(), &limits)?;
///     println!("{path}: {} × {} pixels", image.width(), image.height());
/// }
/// # Ok(())
/// # }
/// ```
#[derive(Debug)]
pub struct FrameReader {
    bytes: Vec<u8>,
    samples: Vec<u8>,
    image: GreyImage,
}

impl Default for FrameReader {
    fn default() -> Self {
        FrameReader {
            bytes: Vec::new(),
            samples: Vec::new(),
            image: GreyImage::unfilled(),
        }
    }
}

impl FrameReader {
    /// Reads and decodes the file at `path` within `limits`; the image lives until the next
    /// call. Grey values as [`GreyImage::open`] gives them.
    pub fn read(&mut self, path: &Path, limits: &DecodeLimits) -> Result<&GreyImage> {
        read_file_into(path, limits, &mut self.bytes)?;
        let reader = checked_reader(&self.bytes, path, limits)?;
        if reader.format() == Some(image::ImageFormat::Pnm) {
            if let Some((size, raster)) = binary_grey8_raster(&self.bytes) {
                // The file's own samples: no decoded copy of a camera-sized frame.
                self.image
                    .assign_decoded(size, image::ColorType::L8, raster)
                    .map_err(|e| read_error(path, e))?;
                return Ok(&self.image);
            }
        }
        let decoder = reader.into_decoder().map_err(|e| read_error(path, e))?;
        let (width, height) = image::ImageDecoder::dimensions(&decoder);
        let colour = image::ImageDecoder::color_type(&decoder);
        let total = usize::try_from(image::ImageDecoder::total_bytes(&decoder))
            .map_err(|e| read_error(path, e))?;
        self.samples.resize(total, 0);
        image::ImageDecoder::read_image(decoder, &mut self.samples)
            .map_err(|e| read_error(path, e))?;
        let size = (width as usize, height as usize);
        let filled = self
            .image
            .assign_decoded(size, colour, &self.samples)
            .map_err(|e| read_error(path, e))?;
        if !filled {
            // Floating-point samples (TIFF): the general path, which checks them.
            let decoded = decode_image_bytes(&self.bytes, path, limits)?;
            self.image = GreyImage::from_dynamic(&decoded).map_err(|e| read_error(path, e))?;
        }
        Ok(&self.image)
    }
}

/// The size and samples of an 8-bit binary PGM (`P5`, largest sample 255) held in `bytes`,
/// as they lie in the file after its header; `None` for any other PNM, or a file too short
/// for its header's size (the decoder then reads it, or says why not).
fn binary_grey8_raster(bytes: &[u8]) -> Option<((usize, usize), &[u8])> {
    use image::codecs::pnm::{PnmDecoder, PnmSubtype, SampleEncoding};
    let (cursor, header) = PnmDecoder::new(std::io::Cursor::new(bytes))
        .ok()?
        .into_inner();
    let binary_grey = header.subtype() == PnmSubtype::Graymap(SampleEncoding::Binary);
    if !binary_grey || header.maximal_sample() != 255 {
        return None;
    }
    let (width, height) = (header.width() as usize, header.height() as usize);
    let start = usize::try_from(cursor.position()).ok()?;
    let raster = bytes.get(start..start.checked_add(width.checked_mul(height)?)?)?;
    Some(((width, height), raster))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A fresh file path under the system's temporary folder.
    fn temp_path(name: &str) -> std::path::PathBuf {
        std::env::temp_dir().join(format!("vernier_image_file_{}_{name}", std::process::id()))
    }

    /// Grey, grey + alpha, RGB, 8 and 16 bit: the reader's buffers, reused across sizes and
    /// layouts, give exactly what a fresh decode gives; a bad file in between is an error
    /// that leaves the next read as it would be.
    #[test]
    fn the_reader_gives_what_a_fresh_decode_gives_frame_after_frame() {
        let (w, h) = (37u32, 23u32);
        let value = |x: u32, y: u32, k: u32| ((x * 7 + y * 13 + k * 29) % 256) as u8;
        let grey8 = image::GrayImage::from_fn(w, h, |x, y| image::Luma([value(x, y, 0)]));
        let grey16 = image::ImageBuffer::<image::Luma<u16>, _>::from_fn(h, w, |x, y| {
            image::Luma([u16::from(value(x, y, 1)) * 256 + 3])
        });
        let rgb8 = image::RgbImage::from_fn(w + 5, h, |x, y| {
            image::Rgb([value(x, y, 0), value(x, y, 1), value(x, y, 2)])
        });
        let la8 =
            image::GrayAlphaImage::from_fn(w, h + 2, |x, y| image::LumaA([value(x, y, 3), 255]));
        let files = [
            ("grey8.pgm", image::DynamicImage::from(grey8.clone())),
            ("grey16.png", image::DynamicImage::from(grey16)),
            ("rgb8.png", image::DynamicImage::from(rgb8)),
            ("la8.png", image::DynamicImage::from(la8)),
            ("grey8_again.png", image::DynamicImage::from(grey8)),
        ];
        let limits = DecodeLimits::default();
        let mut reader = FrameReader::default();
        for (name, picture) in &files {
            let path = temp_path(name);
            picture
                .save(&path)
                .unwrap_or_else(|e| panic!("{name}: {e}"));
            let fresh = GreyImage::open(&path).unwrap_or_else(|e| panic!("{name}: {e}"));
            let read = reader
                .read(&path, &limits)
                .unwrap_or_else(|e| panic!("{name}: {e}"));
            assert_eq!(read, &fresh, "{name}");
            // A truncated copy is refused, and the reader still reads the whole file after.
            let bytes = std::fs::read(&path).unwrap_or_else(|e| panic!("{e}"));
            let truncated = temp_path(&format!("truncated_{name}"));
            std::fs::write(&truncated, &bytes[..bytes.len() / 2]).unwrap_or_else(|e| panic!("{e}"));
            assert!(reader.read(&truncated, &limits).is_err(), "{name}");
            let again = reader
                .read(&path, &limits)
                .unwrap_or_else(|e| panic!("{name}: {e}"));
            assert_eq!(again, &fresh, "{name}");
            let _ = std::fs::remove_file(&path);
            let _ = std::fs::remove_file(&truncated);
        }
        let missing = temp_path("missing.png");
        assert!(reader.read(&missing, &limits).is_err());
    }

    /// Hand-written PGM files, read from the file's own samples (binary, largest sample 255,
    /// a comment in the header) or through the decoder (ASCII, another largest sample), give
    /// what a fresh decode gives; one whose samples stop short is refused.
    #[test]
    fn pgm_files_read_as_a_fresh_decode_reads_them() {
        let (w, h) = (5usize, 3usize);
        let samples: Vec<u8> = (0..w * h).map(|i| (i * 17 % 256) as u8).collect();
        let ascii: Vec<String> = samples.iter().map(|v| (v / 3).to_string()).collect();
        let files: [(&str, Vec<u8>); 4] = [
            (
                "plain.pgm",
                [format!("P5\n{w} {h}\n255\n").into_bytes(), samples.clone()].concat(),
            ),
            (
                "comment.pgm",
                [
                    format!("P5 # made by hand\n{w}\n{h} 255\t").into_bytes(),
                    samples.clone(),
                ]
                .concat(),
            ),
            (
                "maxval.pgm",
                [
                    format!("P5\n{w} {h}\n100\n").into_bytes(),
                    samples.iter().map(|v| v % 101).collect(),
                ]
                .concat(),
            ),
            (
                "ascii.pgm",
                format!("P2\n{w} {h}\n85\n{}\n", ascii.join(" ")).into_bytes(),
            ),
        ];
        let (limits, mut reader) = (DecodeLimits::default(), FrameReader::default());
        for (name, bytes) in &files {
            let path = temp_path(name);
            std::fs::write(&path, bytes).unwrap_or_else(|e| panic!("{e}"));
            let fresh = GreyImage::open(&path).unwrap_or_else(|e| panic!("{name}: {e}"));
            let read = reader
                .read(&path, &limits)
                .unwrap_or_else(|e| panic!("{name}: {e}"));
            assert_eq!(read, &fresh, "{name}");
            assert_eq!((read.width(), read.height()), (w, h), "{name}");
            // The last sample or two cut off.
            std::fs::write(&path, &bytes[..bytes.len() - 4]).unwrap_or_else(|e| panic!("{e}"));
            assert!(reader.read(&path, &limits).is_err(), "{name} cut short");
            let _ = std::fs::remove_file(&path);
        }
        assert_eq!(
            binary_grey8_raster(&files[1].1).map(|r| r.1),
            Some(&samples[..])
        );
    }
}
