/// <reference types="vite/client" />
declare module "*.vue" {
  import type { DefineComponent } from "vue";
  const component: DefineComponent<object, object, unknown>;
  export default component;
}

interface ImportMetaEnv {
  /** "1": the test build, with window.__replay (src/lib/testhook.ts). */
  readonly VITE_TEST_HOOK?: string;
}
