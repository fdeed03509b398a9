//! The frame canvas: one frame-sized image in shared memory that the coordinator owns and
//! the workers on its host write their final spans into, so the frame needs no gather
//! copy and no assembly (IceT's collection likewise lands in the display rank's buffer).
//!
//! The coordinator creates it ([`Canvas::create`]) as a sealed anonymous memory file of
//! exactly `width · height` premultiplied f32 RGBA pixels: sealed against shrinking *and*
//! growing, so the size every side mapped is the size for good. It announces it in the
//! frame request over the authenticated connection; a worker opens it
//! ([`CanvasWriter::open`]) with the same checks as any segment (its name, this user's,
//! sealed; `crate::shm`), and refuses one smaller than the frame.
//!
//! **Trust.** Every worker of the run on this host can write anywhere in the canvas, as it
//! could send any pixels it liked as its final piece: the coordinator checks that the
//! spans the workers report are disjoint and inside the frame and clears what none
//! covers ([`strata_common::composite::canvas::finish`]), but it cannot tell a pixel a
//! worker wrote outside its span. A worker given up on may still hold the mapping, so the
//! coordinator retires a canvas after a failed attempt and never hands out one whose image
//! a caller still holds.

use std::fs::File;

use memmap2::{MmapMut, MmapOptions};
use strata_common::image::Rgba;

use crate::shm::{create_sealed, io_error, open_checked, SegmentId, ShmError};

/// Bytes of one canvas pixel (f32 RGBA).
pub const PIXEL_BYTES: u64 = 16;

/// The canvas's size in bytes for `width × height`, if it is addressable here.
fn byte_len(width: u32, height: u32) -> Option<usize> {
    let len = (width as u64)
        .checked_mul(height as u64)?
        .checked_mul(PIXEL_BYTES)?;
    usize::try_from(len).ok().filter(|&l| l > 0)
}

fn bad_size(name: &str, width: u32, height: u32) -> ShmError {
    io_error(name)(std::io::Error::new(
        std::io::ErrorKind::InvalidInput,
        format!("a canvas of {width}x{height} pixels"),
    ))
}

/// The owner's side: the coordinator's frame.
#[derive(Debug)]
pub struct Canvas {
    file: File,
    name: String,
    map: MmapMut,
    width: u32,
    height: u32,
}

impl Canvas {
    /// A fresh canvas of `width × height` pixels (its memory allocated and mapped).
    pub fn create(width: u32, height: u32) -> Result<Canvas, ShmError> {
        let len = byte_len(width, height).ok_or_else(|| bad_size("canvas", width, height))?;
        let (file, name) = create_sealed(len as u64, libc::F_SEAL_SHRINK | libc::F_SEAL_GROW)?;
        // SAFETY: the file is sealed at exactly `len` bytes (it can neither shrink nor
        // grow), so the whole mapping stays backed.
        let map = unsafe { MmapOptions::new().len(len).populate().map_mut(&file) }
            .map_err(io_error(&name))?;
        Ok(Canvas {
            file,
            name,
            map,
            width,
            height,
        })
    }

    /// What a worker needs to open it.
    pub fn id(&self) -> SegmentId {
        use std::os::fd::AsRawFd;
        SegmentId {
            name: self.name.clone(),
            pid: std::process::id(),
            fd: self.file.as_raw_fd(),
        }
    }

    /// Width and height in pixels.
    pub fn size(&self) -> (u32, u32) {
        (self.width, self.height)
    }

    /// The frame's pixels, row-major.
    pub fn pixels(&self) -> &[Rgba] {
        // A mapping is page-aligned and its length a multiple of 16 bytes.
        bytemuck::cast_slice(&self.map[..])
    }

    /// The frame's pixels, row-major, to finish the frame.
    pub fn pixels_mut(&mut self) -> &mut [Rgba] {
        bytemuck::cast_slice_mut(&mut self.map[..])
    }
}

/// A worker's side: the coordinator's canvas, mapped for writing.
#[derive(Debug)]
pub struct CanvasWriter {
    name: String,
    map: MmapMut,
    width: u32,
    height: u32,
}

impl CanvasWriter {
    /// Opens the canvas the coordinator announced (`id`, over the authenticated
    /// connection) for a `width × height` frame: the memory file of that name, this
    /// user's, sealed against shrinking, and holding at least the frame.
    pub fn open(id: &SegmentId, width: u32, height: u32) -> Result<CanvasWriter, ShmError> {
        let (file, shown) = open_checked(id, true)?;
        let len = byte_len(width, height).ok_or_else(|| bad_size(&shown, width, height))?;
        let size = file.metadata().map_err(io_error(&shown))?.len();
        if size < len as u64 {
            return Err(ShmError::PastEnd {
                offset: 0,
                len: len as u64,
                size,
            });
        }
        // SAFETY: the file is sealed against shrinking (checked at open), so every byte
        // below `size` >= `len` stays backed.
        let map = unsafe { MmapOptions::new().len(len).populate().map_mut(&file) }
            .map_err(io_error(&shown))?;
        Ok(CanvasWriter {
            name: id.name.clone(),
            map,
            width,
            height,
        })
    }

    /// The canvas's name (the key a worker keeps its mappings by).
    pub fn name(&self) -> &str {
        &self.name
    }

    /// Width and height in pixels.
    pub fn size(&self) -> (u32, u32) {
        (self.width, self.height)
    }

    /// The frame's pixels, row-major.
    pub fn pixels_mut(&mut self) -> &mut [Rgba] {
        bytemuck::cast_slice_mut(&mut self.map[..])
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_worker_writes_what_the_owner_reads() {
        let mut c = Canvas::create(5, 3).unwrap();
        c.pixels_mut().fill([9.0; 4]);
        let mut w = CanvasWriter::open(&c.id(), 5, 3).unwrap();
        assert_eq!(w.size(), (5, 3));
        w.pixels_mut()[7] = [0.25, 0.5, 0.75, 1.0];
        assert_eq!(c.pixels()[7], [0.25, 0.5, 0.75, 1.0]);
        assert_eq!(c.pixels()[6], [9.0; 4]);
        assert_eq!(c.pixels().len(), 15);
        // A smaller frame fits; a larger one is refused before mapping.
        assert!(CanvasWriter::open(&c.id(), 3, 3).is_ok());
        assert!(matches!(
            CanvasWriter::open(&c.id(), 5, 4),
            Err(ShmError::PastEnd { .. })
        ));
    }

    #[test]
    fn a_canvas_cannot_be_resized_and_bad_announcements_are_refused() {
        let c = Canvas::create(4, 4).unwrap();
        assert!(c.file.set_len(1024).is_err(), "grown");
        assert!(c.file.set_len(16).is_err(), "shrunk");
        let mut id = c.id();
        id.name = "strata-shm-../../etc".into();
        assert!(matches!(
            CanvasWriter::open(&id, 4, 4),
            Err(ShmError::BadName(_))
        ));
        // A real segment of another name at that descriptor.
        let other = crate::shm::ShmWriter::create().unwrap();
        let mut id = other.id();
        id.name = c.id().name;
        assert!(matches!(
            CanvasWriter::open(&id, 4, 4),
            Err(ShmError::NotPrivate { .. })
        ));
        assert!(Canvas::create(0, 4).is_err());
        assert!(Canvas::create(u32::MAX, u32::MAX).is_err());
    }
}
