//! Depth images in metres.

/// A z-depth image in metres, row-major; `0.0` (or NaN) means "no return".
///
/// ```
/// let mut img = mrfmap::frames::DepthImage::new(4, 3);
/// img.set(1, 2, 1.5);
/// assert_eq!(img.get(1, 2), Some(1.5));
/// assert_eq!(img.get(0, 0), None);
/// ```
#[derive(Clone, Debug, PartialEq)]
pub struct DepthImage {
    width: u32,
    height: u32,
    data: Vec<f32>,
}

impl DepthImage {
    /// An image with no returns.
    pub fn new(width: u32, height: u32) -> Self {
        DepthImage { width, height, data: vec![0.0; width as usize * height as usize] }
    }

    /// Wraps row-major metres; `None` if the length is not `width * height`.
    pub fn from_vec(width: u32, height: u32, data: Vec<f32>) -> Option<Self> {
        (data.len() == width as usize * height as usize).then_some(DepthImage { width, height, data })
    }

    /// Width in pixels.
    pub fn width(&self) -> u32 {
        self.width
    }

    /// Height in pixels.
    pub fn height(&self) -> u32 {
        self.height
    }

    /// Whether depth `z` is a return: not 0, NaN, negative or infinite.
    #[inline]
    pub fn is_valid(z: f32) -> bool {
        z > 0.0 && z.is_finite()
    }

    /// Valid depth at `(u, v)`, `None` for no return (see [`DepthImage::is_valid`]).
    #[inline]
    pub fn get(&self, u: u32, v: u32) -> Option<f32> {
        let z = self.data[v as usize * self.width as usize + u as usize];
        Self::is_valid(z).then_some(z)
    }

    /// Sets the depth at `(u, v)` in metres.
    #[inline]
    pub fn set(&mut self, u: u32, v: u32, z: f32) {
        self.data[v as usize * self.width as usize + u as usize] = z;
    }

    /// One image row.
    pub fn row(&self, v: u32) -> &[f32] {
        let w = self.width as usize;
        &self.data[v as usize * w..(v as usize + 1) * w]
    }

    /// All pixels, row-major.
    pub fn data(&self) -> &[f32] {
        &self.data
    }

    /// Number of pixels with a valid return.
    pub fn valid_count(&self) -> usize {
        self.data.iter().filter(|z| Self::is_valid(**z)).count()
    }
}
