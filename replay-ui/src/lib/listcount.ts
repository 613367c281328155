/**
 * How many a list read page by page holds, in words: "12 floor changes"; with more unread,
 * "at least 199 floor changes (the newest; …)", never "199+", which read as a count.
 *
 * Pure.
 */
export function listCountText(shown: number, more: boolean, one: string, many: string, whatMore: string): string {
  if (!more) return `${shown} ${shown === 1 ? one : many}`;
  return `at least ${shown} ${many} (${whatMore})`;
}
