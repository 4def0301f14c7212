//! A fixed-capacity list of 16-bit words, so frames carry their data without
//! allocating: the capacity is the longest payload the format allows.

use core::fmt;
use core::ops::Deref;

/// Up to `N` words, stored inline. Compares and prints as the slice it holds.
#[derive(Clone, Copy)]
pub struct FixedWords<const N: usize> {
    words: [u16; N],
    len: usize,
}

impl<const N: usize> FixedWords<N> {
    /// The most words this list holds.
    pub const CAPACITY: usize = N;

    /// An empty list.
    pub const fn new() -> Self {
        Self {
            words: [0; N],
            len: 0,
        }
    }

    /// A copy of `words`, or `None` if there are more than `N`.
    pub fn from_slice(words: &[u16]) -> Option<Self> {
        let mut list = Self::new();
        list.words.get_mut(..words.len())?.copy_from_slice(words);
        list.len = words.len();
        Some(list)
    }

    /// Appends `word`; gives it back if the list is full.
    pub fn push(&mut self, word: u16) -> Result<(), u16> {
        let slot = self.words.get_mut(self.len).ok_or(word)?;
        *slot = word;
        self.len += 1;
        Ok(())
    }

    /// The words held, in order.
    pub fn as_slice(&self) -> &[u16] {
        // `len <= N` is kept by every method that changes it.
        &self.words[..self.len]
    }
}

impl<const N: usize> Default for FixedWords<N> {
    fn default() -> Self {
        Self::new()
    }
}

impl<const N: usize> Deref for FixedWords<N> {
    type Target = [u16];
    fn deref(&self) -> &[u16] {
        self.as_slice()
    }
}

impl<const N: usize> PartialEq for FixedWords<N> {
    fn eq(&self, other: &Self) -> bool {
        self.as_slice() == other.as_slice()
    }
}

impl<const N: usize> Eq for FixedWords<N> {}

impl<const N: usize> fmt::Debug for FixedWords<N> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        self.as_slice().fmt(f)
    }
}

#[cfg(test)]
mod tests {
    use super::FixedWords;

    #[test]
    fn holds_at_most_its_capacity() {
        let mut list = FixedWords::<2>::new();
        assert_eq!(list.push(7), Ok(()));
        assert_eq!(list.push(8), Ok(()));
        assert_eq!(list.push(9), Err(9));
        assert_eq!(list.as_slice(), &[7, 8]);
        assert!(FixedWords::<2>::from_slice(&[1, 2, 3]).is_none());
        let mut one = FixedWords::<2>::new();
        assert_eq!(one.push(1), Ok(()));
        assert_eq!(FixedWords::<2>::from_slice(&[1]), Some(one));
        assert_ne!(FixedWords::<2>::from_slice(&[1, 2]), Some(one));
    }
}
