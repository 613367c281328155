// Rules that find bugs, not a house style: ESLint's and typescript-eslint's recommended
// sets, eslint-plugin-vue's "essential" (errors, no formatting), and the type-aware rules
// that catch a promise nobody awaits or handles.
import js from "@eslint/js";
import pluginVue from "eslint-plugin-vue";
import globals from "globals";
import tseslint from "typescript-eslint";

export default tseslint.config(
  { ignores: ["dist/", "dist-test/", "node_modules/", "src/lib/api-schema.d.ts"] },
  js.configs.recommended,
  ...tseslint.configs.recommended,
  ...pluginVue.configs["flat/essential"],
  {
    files: ["**/*.ts", "**/*.vue"],
    languageOptions: {
      globals: { ...globals.browser },
      parserOptions: {
        parser: tseslint.parser,
        projectService: true,
        extraFileExtensions: [".vue"],
        tsconfigRootDir: import.meta.dirname,
      },
    },
    rules: {
      "@typescript-eslint/no-floating-promises": "error",
      "@typescript-eslint/no-misused-promises": "error",
      // The panels get the state object of a composable (useAnnotations, useCommands) as a
      // prop and bind its form fields: replacing the prop would be the bug, not that.
      "vue/no-mutating-props": ["error", { shallowOnly: true }],
    },
  },
  {
    // The two pages' root components, mounted by main.ts / controller.ts, never used as a
    // tag, so a one-word name cannot clash with an HTML element.
    files: ["src/App.vue", "src/Controller.vue"],
    rules: { "vue/multi-word-component-names": "off" },
  },
  {
    files: ["tests/**/*.ts", "vite.config.ts", "eslint.config.js"],
    languageOptions: { globals: { ...globals.node } },
  },
);
